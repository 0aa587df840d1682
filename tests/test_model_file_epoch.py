"""Epochs count from 1 everywhere: the model file says the best epoch the training metrics say, and a model file
of format 2 (epoch counted from 0) is read with its epoch counted from 1."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from endoflow.config import Params
from endoflow.models.model_file import ModelRecord, TrainingBaselines, load_model_file, save_model_file
from endoflow.training.checkpoint import BestEpoch, TrainState
from endoflow.training.ray_trainer import write_training_outputs

BASELINES = TrainingBaselines(5.0, np.ones((4, 4), np.float32), np.eye(4))


def test_the_model_file_names_the_best_epoch_the_training_metrics_name(tmp_path: Path) -> None:
    history = [{"epoch": e + 1, "train_loss": 1.0 / (e + 1), "val_abs_rel": 0.5} for e in range(10)]
    state = TrainState(epoch=9, global_step=20, history=history,
                       best=BestEpoch(epoch=8, val={"val_abs_rel": 0.2}, model={"w": torch.zeros(2)}))
    summary = write_training_outputs(Params(), tmp_path, state, "run-1", BASELINES, "fingerprint")
    assert summary["best_epoch"] == 9 and load_model_file(tmp_path / Params().train.out).epoch == 9


def test_a_format_2_model_file_is_read_with_its_epoch_counted_from_1(tmp_path: Path) -> None:
    path = tmp_path / "endoflow.pt"
    save_model_file(path, ModelRecord(Params(), {"w": torch.zeros(2)}, 8, {}, None, BASELINES))
    assert load_model_file(path).epoch == 8
    raw = torch.load(path, weights_only=True)
    torch.save({**raw, "format": 2}, path)
    assert load_model_file(path).epoch == 9

"""The model file and the training state load as tensors and plain data only, and say which file is wrong.

The audit's case: a ``state.pt`` planted in the Ray storage path ran code when ``train`` resumed
(``torch.load(weights_only=False)``). Now every file endoflow loads is read with ``weights_only=True``.
"""

from __future__ import annotations

import errno
import os
import random
from pathlib import Path

import numpy as np
import pytest
import torch

from endoflow import tracking
from endoflow.config import Params
from endoflow.errors import DataFormatError
from endoflow.models.endoflow_model import load_trained_model
from endoflow.models.model_file import ModelRecord, TrainingBaselines, load_model_file, save_model_file
from endoflow.training.checkpoint import (
    BestEpoch,
    TrainingCheckpoint,
    TrainState,
    load_random_state,
    load_training_state,
    random_state,
    restore_random_state,
    save_random_state,
    save_training_state,
)
from endoflow.training.ray_trainer import train, training_fingerprint


class Payload:
    """Unpickling this creates ``target``: proof that loading ran code."""

    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self):
        return (Path.touch, (self.target,))


def plant(path: Path, target: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state": Payload(target), "model": {}}, path)


def small_checkpoint() -> TrainingCheckpoint:
    layer = torch.nn.Linear(3, 2)
    optimizer = torch.optim.AdamW(layer.parameters(), lr=1e-3)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=4)
    layer(torch.ones(1, 3)).sum().backward()
    optimizer.step()
    scheduler.step()
    state = TrainState(epoch=1, global_step=7, best=BestEpoch(0, {"val_abs_rel": 0.25}, layer.state_dict()),
                       history=[{"epoch": 0, "lr": 1e-3, "train_loss": 0.5, "val_abs_rel": 0.25}])
    return TrainingCheckpoint(state, layer.state_dict(), optimizer.state_dict(), scheduler.state_dict())


def test_training_state_round_trips_through_a_weights_only_load(tmp_path: Path) -> None:
    saved = small_checkpoint()
    save_training_state(tmp_path, saved)
    loaded = load_training_state(tmp_path)
    assert loaded.state.epoch == 1 and loaded.state.global_step == 7 and loaded.state.history == saved.state.history
    assert loaded.state.best.epoch == 0 and loaded.state.best.val == {"val_abs_rel": 0.25}
    assert all(torch.equal(loaded.model[k], v) for k, v in saved.model.items())
    assert loaded.scheduler == saved.scheduler
    assert torch.equal(loaded.optimizer["state"][0]["exp_avg"], saved.optimizer["state"][0]["exp_avg"])


def test_a_planted_state_file_that_would_run_code_is_refused_naming_it(tmp_path: Path) -> None:
    plant(tmp_path / "state.pt", tmp_path / "payload-ran")
    with pytest.raises(DataFormatError, match="could run code") as caught:
        load_training_state(tmp_path)
    assert str(tmp_path / "state.pt") in str(caught.value)
    assert not (tmp_path / "payload-ran").exists()


def test_a_model_file_that_would_run_code_or_is_damaged_is_refused_naming_it(tmp_path: Path) -> None:
    plant(tmp_path / "evil.pt", tmp_path / "payload-ran")
    with pytest.raises(DataFormatError, match="could run code") as caught:
        load_model_file(tmp_path / "evil.pt")
    assert str(tmp_path / "evil.pt") in str(caught.value) and not (tmp_path / "payload-ran").exists()

    record = ModelRecord(Params(), {"w": torch.ones(2)}, 3, {"val_abs_rel": 0.1}, None,
                         TrainingBaselines(5.0, np.ones((4, 4), np.float32), np.eye(4)))
    save_model_file(tmp_path / "model.pt", record)
    assert load_model_file(tmp_path / "model.pt").epoch == 3
    data = (tmp_path / "model.pt").read_bytes()
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    torch.save({"format": 99}, tmp_path / "other.pt")
    record.state = {"not.a.layer": torch.ones(2)}
    save_model_file(tmp_path / "mismatch.pt", record)
    with pytest.raises(DataFormatError, match="weights do not fit") as caught:
        load_trained_model(tmp_path / "mismatch.pt", torch.device("cpu"))
    assert str(tmp_path / "mismatch.pt") in str(caught.value)
    for name, problem in (("truncated.pt", "not a readable torch file"), ("other.pt", "format 99")):
        with pytest.raises(DataFormatError, match=problem) as caught:
            load_model_file(tmp_path / name)
        assert str(tmp_path / name) in str(caught.value)


def test_every_random_generator_continues_where_it_was_saved(tmp_path: Path) -> None:
    torch.manual_seed(1), np.random.seed(2), random.seed(3)
    save_random_state(tmp_path, rank=1)
    expected = (torch.rand(3), np.random.rand(3), random.random())
    torch.manual_seed(9), np.random.seed(9), random.seed(9)
    restore_random_state(load_random_state(tmp_path, rank=1))
    again = (torch.rand(3), np.random.rand(3), random.random())
    assert torch.equal(expected[0], again[0]) and np.array_equal(expected[1], again[1]) and expected[2] == again[2]
    assert load_random_state(tmp_path, rank=0) is None
    assert set(random_state()) == {"torch", "cuda", "numpy", "python"}


def test_train_refuses_a_planted_checkpoint_before_ray_starts_and_marks_the_run_failed(
    tmp_path: Path, monkeypatch
) -> None:
    from tests.test_ray import project

    params = project(tmp_path)
    storage = tmp_path / "checkpoints"
    params.ray = params.ray.replace(storage_path=str(storage))
    shards = str(tmp_path / params.train.shards)
    run = storage / f"{params.ray.run_name}-{training_fingerprint(params, shards, None)}"
    plant(run / "epoch-0000" / "state.pt", tmp_path / "payload-ran")
    save_random_state(run / "epoch-0000", rank=0)  # an otherwise complete checkpoint folder

    def ray_must_not_start(*_args, **_kwargs):
        raise AssertionError("Ray was started although the checkpoint to resume from is unsafe")

    monkeypatch.setattr("endoflow.training.ray_trainer.fit_on_ray", ray_must_not_start)
    with pytest.raises(DataFormatError, match="could run code") as caught:
        train(params, tmp_path)

    assert str(run / "epoch-0000" / "state.pt") in str(caught.value)
    assert not (tmp_path / "payload-ran").exists()
    uri = tracking.tracking_uri(params, tmp_path)
    runs = tracking.client(uri).search_runs([tracking.ensure_experiment(params, tmp_path, "endoflow")])
    assert [r.info.status for r in runs] == ["FAILED"]


def test_a_corrupted_latent_bank_fails_before_ray_starts_naming_the_file(tmp_path: Path, monkeypatch) -> None:
    from tests.test_ray import project

    params = project(tmp_path)
    bank = tmp_path / "models" / "latent_bank.pt"
    bank.parent.mkdir(parents=True)
    bank.write_bytes(b"PK\x03\x04" + bytes(200))  # a zip header, then damage
    params.model = params.model.replace(latent_bank=True)
    params.train = params.train.replace(latent_bank=str(bank))

    def ray_must_not_start(*_args, **_kwargs):
        raise AssertionError("Ray was started with an unreadable latent bank")

    monkeypatch.setattr("endoflow.training.ray_trainer.fit_on_ray", ray_must_not_start)

    with pytest.raises(DataFormatError, match="truncated or corrupt") as caught:
        train(params, tmp_path)

    assert str(bank) in str(caught.value)
    assert not (tmp_path / "mlflow.db").exists()  # checked before any MLflow run is opened


def test_workers_the_cluster_cannot_hold_fail_naming_the_key_and_the_run_is_failed(tmp_path: Path) -> None:
    from endoflow.config import ConfigError
    from tests.test_ray import project

    params = project(tmp_path)
    params.ray = params.ray.replace(num_cpus=None, cpus_per_worker=64.0, storage_path=str(tmp_path / "ray"))

    with pytest.raises(ConfigError, match="ray.cpus_per_worker") as caught:
        train(params, tmp_path)

    assert "rerun the stage" not in str(caught.value)
    uri = tracking.tracking_uri(params, tmp_path)
    runs = tracking.client(uri).search_runs([tracking.ensure_experiment(params, tmp_path, "endoflow")])
    assert [r.info.status for r in runs] == ["FAILED"]


def test_the_worker_config_survives_pickling_and_a_misspelt_field_fails_on_the_driver() -> None:
    import pickle

    from endoflow.training.worker_config import WorkerConfig

    config = WorkerConfig(Params(), (("/s/train-000000.tar",),), (), None, "sqlite:///m.db", "run", resume_from=None,
                          batch_shares=(12,))
    assert pickle.loads(pickle.dumps(config)) == config
    with pytest.raises(ValueError, match="one batch share per train folder"):
        WorkerConfig(Params(), (("/s/train-000000.tar",), ("/v/train-000000.tar",)), (), None, "", "", None,
                     batch_shares=(12,))
    with pytest.raises(TypeError, match="train_shard"):
        WorkerConfig(Params(), train_shard=(), val_shards=(), latent_bank=None, tracking_uri="", run_id="",
                     resume_from=None)


# ---------------------------------------------------------------------- what a failed training advises
class WorkerGroupFailure(Exception):
    """Ray's wrapping of worker errors: ``worker_failures`` maps a rank to its error."""

    def __init__(self, failures: dict) -> None:
        super().__init__("Training failed due to worker errors")
        self.worker_failures = failures


def test_rerun_is_advised_only_where_it_helps() -> None:
    from endoflow.training.loop import NonFiniteLossError
    from endoflow.training.ray_trainer import training_failure

    storage = "/project/checkpoints"
    shard = "/project/data/shards/simcol/val-000000.tar"
    repeating = {
        "damaged validation shard": DataFormatError(shard, "SHA-256 differs from the manifest's"),
        "refused random state": DataFormatError(f"{storage}/run/epoch-0001/rng-rank-0.pt", "refused to load"),
        "full disk": OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), f"{storage}/run/epoch-0002/state.pt"),
        "non-finite loss": NonFiniteLossError("non-finite training loss at epoch 1, step 1; lower train.lr"),
    }
    for case, error in repeating.items():
        message = training_failure(WorkerGroupFailure({1: error, 0: error}), storage)
        assert "rerun the stage to resume" not in message or "disk" in message, case
        assert str(error) in message, case
    assert f"until {shard} is rebuilt or removed" in training_failure(repeating["damaged validation shard"], storage)
    assert f"ray.storage_path {storage}" in training_failure(repeating["full disk"], storage)

    lost = training_failure(WorkerGroupFailure({0: RuntimeError("the worker's node was lost")}), storage)
    assert lost == ("training failed: RuntimeError: the worker's node was lost (rerun the stage to resume from "
                    "the last checkpoint)")


def test_a_full_disk_during_training_names_the_storage_path_and_fails_the_run(tmp_path: Path, monkeypatch) -> None:
    from endoflow.training.ray_trainer import TrainingError
    from tests.test_ray import project

    params = project(tmp_path)
    params.ray = params.ray.replace(storage_path=str(tmp_path / "checkpoints"))

    def disk_full_on_the_workers(*_args, **_kwargs):
        raise WorkerGroupFailure({0: OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))})

    monkeypatch.setattr("endoflow.training.ray_trainer.fit_on_ray", disk_full_on_the_workers)
    with pytest.raises(TrainingError, match=r"No space left on device \(a rerun repeats this") as caught:
        train(params, tmp_path)

    assert f"ray.storage_path {tmp_path / 'checkpoints'}" in str(caught.value)
    uri = tracking.tracking_uri(params, tmp_path)
    runs = tracking.client(uri).search_runs([tracking.ensure_experiment(params, tmp_path, "endoflow")])
    assert [r.info.status for r in runs] == ["FAILED"]


def test_a_lost_tracking_server_neither_stalls_training_nor_hides_its_error(tmp_path: Path, monkeypatch,
                                                                             capsys) -> None:
    import json
    import time

    from endoflow.training.ray_trainer import TrainingError
    from tests.test_ray import project
    from tests.test_tracking import lost_server_uri

    params = project(tmp_path)
    params.tracking.uri = lost_server_uri(monkeypatch)

    def opened_before_the_server_was_lost(run_params, root, *_args, **_kwargs) -> tracking.RunHandle:
        return tracking.RunHandle.attach(tracking.tracking_uri(run_params, root), "run0",
                                         tracking.project_unlogged_file(root, "run0"))

    def node_lost(*_args, **_kwargs):
        raise RuntimeError("the worker's node was lost")

    monkeypatch.setattr(tracking, "start_run", opened_before_the_server_was_lost)
    monkeypatch.setattr("endoflow.training.ray_trainer.fit_on_ray", node_lost)
    started = time.monotonic()
    with pytest.raises(TrainingError, match="the worker's node was lost"):
        train(params, tmp_path)

    assert time.monotonic() - started < 30
    assert capsys.readouterr().err.count(f"warning: MLflow at {params.tracking.uri}") == 1
    kept = tracking.project_unlogged_file(tmp_path, "run0").read_text().splitlines()
    assert json.loads(kept[-1])["status"] == "FAILED"


def test_the_ray_log_folder_of_a_killed_training_is_removed_by_the_next(tmp_path: Path, monkeypatch) -> None:
    import tempfile

    from endoflow.training.ray_trainer import RAY_LOG_TEMPORARY, TrainingError
    from tests.test_atomic_writes import ended_process_mark
    from tests.test_ray import project

    params = project(tmp_path)
    temporary = tmp_path / "tmp"
    killed = temporary / f"{RAY_LOG_TEMPORARY}{ended_process_mark()}-k1ll3d00"
    (killed / "ray-from-epoch-0001.log").parent.mkdir(parents=True)
    (killed / "ray-from-epoch-0001.log").write_text("(RayTrainWorker pid=7) [train] epoch 1/2 step 1/1\n")
    monkeypatch.setattr(tempfile, "tempdir", str(temporary))

    def node_lost(*_args, **_kwargs):
        raise RuntimeError("the worker's node was lost")

    monkeypatch.setattr("endoflow.training.ray_trainer.fit_on_ray", node_lost)
    with pytest.raises(TrainingError):
        train(params, tmp_path)

    assert list(temporary.iterdir()) == []  # the killed run's folder, and this run's own

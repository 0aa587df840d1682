"""The model file (``train.out``, ``models/endoflow.pt``): what training writes and evaluation reads.

A plain ``torch.save`` dict, loaded with ``weights_only=True`` (tensors and plain data only, so loading
cannot execute code): ``format`` (:data:`MODEL_FORMAT`), ``model`` (state dict of the best validation epoch),
``params`` (nested dict: the architecture is rebuilt from it), ``epoch`` (that epoch, counted from 1 as the
training history and metrics count), ``val`` (its validation metrics),
``mlflow_run_id`` (the training run, where ``evaluate`` logs too; for an adapted model, its adaptation run),
``baselines`` (training-set statistics for the trivial baselines of the evaluation) and, for a model ``endoflow
adapt`` fitted to a video, ``adapted_from`` (its parent: model file, SHA-256, MLflow run; the input, steps and the
held-out photometric error before and after). The state dict holds the learned cameras' intrinsics
(``intrinsics.corrections``, :mod:`endoflow.models.intrinsics`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from endoflow.config import ConfigError, Params, params_from_dict, params_to_dict
from endoflow.errors import DataFormatError
from endoflow.io import load_plain_torch_file, save_torch

# 2: the latent bank's init-scaled convolutions carry an init_scale buffer in the state dict.
MODEL_FORMAT = 3
# 3: the epoch counted from 1. 2: the same file with the epoch counted from 0, read as format 3.
READ_FORMATS = (2, 3)


@dataclass
class TrainingBaselines:
    """Training-set statistics behind the evaluation's trivial baselines.

    Attributes:
        mean_depth_cm: mean of all valid GT depth pixels (the constant-depth baseline).
        mean_depth_map: ``H x W`` per-pixel mean of valid GT depth at the stored size (float32).
        mean_relative_pose: ``4 x 4`` mean ``inv(P_i) @ P_{i+1}`` over consecutive frames ``i``, ``i + 1``
            (the constant-velocity baseline; from training pairs further apart, their per-frame root).
    """

    mean_depth_cm: float
    mean_depth_map: np.ndarray
    mean_relative_pose: np.ndarray

    def to_record(self) -> dict[str, Any]:
        return {"mean_depth_cm": float(self.mean_depth_cm),
                "mean_depth_map": torch.from_numpy(np.asarray(self.mean_depth_map, np.float32)),
                "mean_relative_pose": torch.from_numpy(np.asarray(self.mean_relative_pose, np.float64))}

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> "TrainingBaselines":
        return cls(float(record["mean_depth_cm"]), record["mean_depth_map"].numpy(),
                   record["mean_relative_pose"].numpy())


@dataclass
class ModelRecord:
    params: Params
    state: dict[str, torch.Tensor]
    epoch: int
    val: dict[str, float]
    mlflow_run_id: Optional[str]
    baselines: TrainingBaselines
    adapted_from: Optional[dict[str, Any]] = None


def save_model_file(path: str | Path, record: ModelRecord) -> None:
    """Write the model file atomically."""
    save_torch(path, {
        "format": MODEL_FORMAT,
        "model": record.state,
        "params": params_to_dict(record.params),
        "epoch": record.epoch,
        "val": dict(record.val),
        "mlflow_run_id": record.mlflow_run_id,
        "baselines": record.baselines.to_record(),
        **({"adapted_from": dict(record.adapted_from)} if record.adapted_from is not None else {}),
    })


def load_model_file(path: str | Path) -> ModelRecord:
    """Read a model file written by :func:`save_model_file`.

    Raises:
        FileNotFoundError: no file at ``path``.
        DataFormatError: naming ``path``: not a torch file, a file that would run code, or another format.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: model file not found (run the train stage first)")
    raw = load_plain_torch_file(path, "an endoflow model file")
    if not isinstance(raw, dict) or raw.get("format") not in READ_FORMATS:
        found = raw.get("format") if isinstance(raw, dict) else type(raw).__name__
        raise DataFormatError(path, f"model file format {found!r}, expected {MODEL_FORMAT} (an endoflow model file "
                                    f"written by the train stage)")
    try:
        params = params_from_dict(raw["params"])
    except ConfigError as exc:
        raise DataFormatError(path, f"the params stored in the model file are not valid: {exc}") from None
    epoch = int(raw["epoch"]) + (1 if raw["format"] == 2 else 0)
    return ModelRecord(params=params, state=raw["model"], epoch=epoch, val=raw["val"],
                       mlflow_run_id=raw["mlflow_run_id"], baselines=TrainingBaselines.from_record(raw["baselines"]),
                       adapted_from=raw.get("adapted_from"))

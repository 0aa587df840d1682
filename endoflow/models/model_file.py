"""The model file (``train.out``, ``models/endoflow.pt``): what training writes and evaluation reads.

A plain ``torch.save`` dict, loaded with ``weights_only=True`` (tensors and plain data only, so loading
cannot execute code): ``format`` (:data:`MODEL_FORMAT`), ``model`` (state dict of the best validation epoch),
``params`` (nested dict: the architecture is rebuilt from it), ``epoch``, ``val`` (its validation metrics),
``mlflow_run_id`` (the training run, where ``evaluate`` logs too) and ``baselines`` (training-set statistics
for the trivial baselines of the evaluation).
"""

from __future__ import annotations

import io
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from endoflow.config import ConfigError, Params, params_from_dict, params_to_dict
from endoflow.data.base import DataFormatError
from endoflow.io import save_torch

# 2: the latent bank's init-scaled convolutions carry an init_scale buffer in the state dict.
MODEL_FORMAT = 2
_ZIP_MAGIC = b"PK\x03\x04"


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
    if not isinstance(raw, dict) or raw.get("format") != MODEL_FORMAT:
        found = raw.get("format") if isinstance(raw, dict) else type(raw).__name__
        raise DataFormatError(path, f"model file format {found!r}, expected {MODEL_FORMAT} (an endoflow model file "
                                    f"written by the train stage)")
    try:
        params = params_from_dict(raw["params"])
    except ConfigError as exc:
        raise DataFormatError(path, f"the params stored in the model file are not valid: {exc}") from None
    return ModelRecord(params=params, state=raw["model"], epoch=int(raw["epoch"]), val=raw["val"],
                       mlflow_run_id=raw["mlflow_run_id"], baselines=TrainingBaselines.from_record(raw["baselines"]))


def load_trained_model(path: str | Path, device: torch.device) -> tuple[torch.nn.Module, ModelRecord]:
    """The trained model in eval mode on ``device``, rebuilt from the params stored with it."""
    from endoflow.models.endoflow_model import build_model

    record = load_model_file(path)
    # the bank's weights are part of the state dict: build an empty one, then load everything
    model = build_model(record.params, latent_bank_path=None)
    try:
        model.load_state_dict(record.state)
    except RuntimeError as exc:  # missing, unexpected or misshapen tensors
        raise DataFormatError(path, f"weights do not fit the architecture of its params "
                                    f"({' '.join(str(exc).split())[:300]})") from None
    return model.to(device).eval(), record


def load_plain_torch_file(source: str | Path | bytes, what: str, name: Optional[str] = None) -> Any:
    """``torch.load(weights_only=True)`` of a path or of a file's bytes, with errors that name the file.

    Anything that needs more than tensors and plain data to load (a pickled object, which could run code)
    is refused, as is a file that is not a torch archive at all (``torch.save`` writes zip archives).
    """
    label = name or str(source)
    data = source if isinstance(source, bytes) else Path(source).read_bytes()
    if not data.startswith(_ZIP_MAGIC):
        raise DataFormatError(label, f"not a torch file (no zip archive header: truncated, empty or another kind of "
                                     f"file); expected {what}")
    try:
        return torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's text goes on to explain how to allowlist the global: advice we do not pass on
        reason = next((line.strip() for line in str(exc).splitlines() if "Unsupported" in line), "").split(". ")[0]
        raise DataFormatError(label, f"refused to load: it holds objects other than tensors and plain data, which "
                                     f"could run code ({reason or 'weights-only load failed'}); expected {what}") from None
    except (RuntimeError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:  # how torch reports damage
        raise DataFormatError(label, f"not a readable torch file, truncated or corrupt ({str(exc).splitlines()[0][:200]}); "
                                     f"expected {what}") from None

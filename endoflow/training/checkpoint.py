"""What training leaves behind: Ray checkpoints of the full training state, and the final model file.

Ray checkpoint folder (one per finished epoch, persisted by Ray to its storage path)::

    state.pt        rank 0: model, optimiser, scheduler, epoch, global step, best model so far, history
    rank-<r>.json   every rank: the sample keys it trained on this epoch and a SHA-256 of its weights
                    (an audit of data parallelism: weights must agree, keys must be disjoint)

Model file (``train.out``, ``models/endoflow.pt``), a plain ``torch.save`` dict readable with
``weights_only=True``: ``format``, ``model`` (state dict of the best validation epoch), ``params`` (nested
dict: the architecture is rebuilt from it), ``epoch``, ``val`` (its validation metrics), ``mlflow_run_id``
(the training run, where ``evaluate`` logs too) and ``baselines`` (training-set statistics for the trivial
baselines of the evaluation).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import fsspec
import numpy as np
import torch

from endoflow.config import Params, params_from_dict, params_to_dict

MODEL_FORMAT = 1
STATE_FILE = "state.pt"


@dataclass
class TrainingBaselines:
    """Training-set statistics behind the evaluation's trivial baselines.

    Attributes:
        mean_depth_cm: mean of all valid GT depth pixels (the constant-depth baseline).
        mean_depth_map: ``H x W`` per-pixel mean of valid GT depth at the stored size (float32).
        mean_relative_pose: ``4 x 4`` mean ``inv(P_i) @ P_{i+1}`` (the constant-velocity baseline).
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
    """Write the model file atomically (temporary name, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save({
        "format": MODEL_FORMAT,
        "model": record.state,
        "params": params_to_dict(record.params),
        "epoch": record.epoch,
        "val": dict(record.val),
        "mlflow_run_id": record.mlflow_run_id,
        "baselines": record.baselines.to_record(),
    }, tmp)
    os.replace(tmp, path)


def load_model_file(path: str | Path) -> ModelRecord:
    """Read a model file written by :func:`save_model_file` (tensors only, no pickled code)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: model file not found (run the train stage first)")
    raw = torch.load(path, map_location="cpu", weights_only=True)
    if raw.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: model file format {raw.get('format')!r}, expected {MODEL_FORMAT}")
    return ModelRecord(params=params_from_dict(raw["params"]), state=raw["model"], epoch=int(raw["epoch"]),
                       val=raw["val"], mlflow_run_id=raw["mlflow_run_id"],
                       baselines=TrainingBaselines.from_record(raw["baselines"]))


def load_trained_model(path: str | Path, device: torch.device) -> tuple[torch.nn.Module, ModelRecord]:
    """The trained model in eval mode on ``device``, rebuilt from the params stored with it."""
    from endoflow.models.endoflow_model import build_model

    record = load_model_file(path)
    # the bank's weights are part of the state dict: build an empty one, then load everything
    model = build_model(record.params, latent_bank_path=None)
    model.load_state_dict(record.state)
    return model.to(device).eval(), record


def weights_digest(model: torch.nn.Module) -> str:
    """SHA-256 over every parameter and buffer, in name order (equal digests = identical weights)."""
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def save_training_state(directory: Path, state: dict[str, Any]) -> None:
    torch.save(state, directory / STATE_FILE)


def load_training_state(checkpoint: str | Path) -> dict[str, Any]:
    """``state.pt`` of a checkpoint folder given as a local path or an fsspec URL."""
    with fsspec.open(f"{str(checkpoint).rstrip('/')}/{STATE_FILE}", "rb") as f:
        return torch.load(io.BytesIO(f.read()), map_location="cpu", weights_only=False)


def latest_checkpoint(run_location: str) -> Optional[str]:
    """The newest ``epoch-NNNN`` checkpoint under a Ray run folder (path or fsspec URL) whose ``state.pt``
    is complete, or ``None``. A run killed while Ray copied a checkpoint leaves a truncated file, which
    fails the zip check here (``torch.save`` writes zip archives) and is skipped."""
    fs, root = fsspec.core.url_to_fs(run_location)
    folders = sorted(fs.glob(f"{root.rstrip('/')}/epoch-*"), reverse=True)
    for folder in folders:
        try:
            with fs.open(f"{folder}/{STATE_FILE}", "rb") as f, zipfile.ZipFile(f):
                pass
        except (OSError, zipfile.BadZipFile):
            continue
        return fs.unstrip_protocol(folder) if "://" in run_location else folder
    return None


def write_rank_audit(directory: Path, rank: int, epoch: int, keys: list[str], digest: str) -> None:
    (directory / f"rank-{rank}.json").write_text(
        json.dumps({"rank": rank, "epoch": epoch, "weights_sha256": digest, "keys": keys}))


def read_rank_audits(directory: Path) -> list[dict[str, Any]]:
    """The ``rank-<r>.json`` audits of one checkpoint folder, by rank."""
    return sorted((json.loads(p.read_text()) for p in Path(directory).glob("rank-*.json")),
                  key=lambda audit: audit["rank"])

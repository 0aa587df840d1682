"""The training state: what a Ray checkpoint holds, so that an interrupted run resumes exactly.

One folder per finished epoch: ``state.pt`` (rank 0: model, optimiser, scheduler and :class:`TrainState`, with the
best epoch's weights), ``rng-rank-<r>.pt`` and ``rank-<r>.json`` (every rank); tensors and plain data, loaded
weights-only. See docs/outputs.md, "`train`".
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import zipfile
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Optional

import fsspec
import numpy as np
import torch

from endoflow.errors import DataFormatError
from endoflow.io import load_plain_torch_file, save_torch, write_text

STATE_FILE = "state.pt"
TRAINING_STATE = "an endoflow training state (state.pt of a Ray checkpoint)"


@dataclass
class BestEpoch:
    """The epoch with the best validation so far and a CPU copy of its weights."""

    epoch: int
    val: dict[str, float]
    model: dict[str, torch.Tensor]


@dataclass
class TrainState:
    """Progress of a training run: ``epoch`` is the last finished one (-1 before the first)."""

    epoch: int = -1
    global_step: int = 0
    best: Optional[BestEpoch] = None
    history: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class TrainingCheckpoint:
    """Everything rank 0 saves after an epoch."""

    state: TrainState
    model: dict[str, torch.Tensor]
    optimizer: dict[str, Any]
    scheduler: dict[str, Any]


def save_training_state(directory: Path, checkpoint: TrainingCheckpoint) -> None:
    """Write ``state.pt`` into a checkpoint folder."""
    save_torch(Path(directory) / STATE_FILE, {
        # field by field: asdict would deep-copy the best epoch's weights on every save
        "state": {f.name: getattr(checkpoint.state, f.name) for f in fields(TrainState) if f.name != "best"},
        "best": None if checkpoint.state.best is None else vars(checkpoint.state.best),
        "model": checkpoint.model,
        "optimizer": checkpoint.optimizer,
        "scheduler": checkpoint.scheduler,
    })


def load_training_state(checkpoint: str | Path) -> TrainingCheckpoint:
    """``state.pt`` of a checkpoint folder given as a local path or an fsspec URL.

    Raises:
        DataFormatError: naming the file, when it is not a training state of this format or would run code.
    """
    location = f"{str(checkpoint).rstrip('/')}/{STATE_FILE}"
    raw = load_plain_torch_file(_read_bytes(location), TRAINING_STATE, name=location)
    try:
        state = TrainState(**raw["state"], best=None)
        state.best = None if raw["best"] is None else BestEpoch(**raw["best"])
        return TrainingCheckpoint(state, raw["model"], raw["optimizer"], raw["scheduler"])
    except (KeyError, TypeError) as exc:
        raise DataFormatError(location, f"not {TRAINING_STATE} of this endoflow version ({exc})") from None


# ---------------------------------------------------------------------------------------- random state
def rng_file(rank: int) -> str:
    return f"rng-rank-{rank}.pt"


def random_state() -> dict[str, Any]:
    """The torch (CPU and every CUDA device), NumPy and Python random states, as tensors and plain data."""
    kind, keys, position, has_gauss, gauss = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "position": int(position),
                  "has_gauss": int(has_gauss), "gauss": float(gauss)},
        "python": random.getstate(),
    }


def restore_random_state(saved: dict[str, Any]) -> None:
    """Undo :func:`random_state`: every generator continues exactly where it was saved."""
    torch.set_rng_state(saved["torch"])
    if saved["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(saved["cuda"])
    numpy = saved["numpy"]
    np.random.set_state((numpy["kind"], numpy["keys"].numpy().astype(np.uint32), numpy["position"],
                         numpy["has_gauss"], numpy["gauss"]))
    version, internal, gauss = saved["python"]
    random.setstate((version, tuple(internal), gauss))


def save_random_state(directory: Path, rank: int) -> None:
    save_torch(Path(directory) / rng_file(rank), random_state())


def load_random_state(checkpoint: str | Path, rank: int) -> Optional[dict[str, Any]]:
    """The random state ``rank`` saved in a checkpoint folder, or ``None`` when it has none."""
    location = f"{str(checkpoint).rstrip('/')}/{rng_file(rank)}"
    fs, path = fsspec.core.url_to_fs(location)
    if not fs.exists(path):
        return None
    return load_plain_torch_file(_read_bytes(location), "an endoflow random state", name=location)


# ------------------------------------------------------------------------------------------ finding
def latest_checkpoint(run_location: str, ranks: int) -> Optional[str]:
    """The newest ``epoch-NNNN`` checkpoint under a Ray run folder (path or fsspec URL) that is complete, or
    ``None``: a ``state.pt`` and the random state of each of ``ranks`` ranks, all whole. A run killed while
    Ray copied a checkpoint leaves files missing or truncated (``torch.save`` writes zip archives, so a cut
    file fails the zip check); such a folder is skipped for the one before it."""
    fs, root = fsspec.core.url_to_fs(run_location)
    folders = sorted(fs.glob(f"{root.rstrip('/')}/epoch-*"), reverse=True)
    for folder in folders:
        names = [STATE_FILE, *(rng_file(rank) for rank in range(ranks))]
        if all(_is_whole_zip(fs, f"{folder}/{name}") for name in names):
            return fs.unstrip_protocol(folder) if "://" in run_location else folder
    return None


def _is_whole_zip(fs: Any, path: str) -> bool:
    try:
        with fs.open(path, "rb") as f, zipfile.ZipFile(f):
            return True
    except (OSError, zipfile.BadZipFile):
        return False


# --------------------------------------------------------------------------------------------- audit
def weights_digest(model: torch.nn.Module) -> str:
    """SHA-256 over every parameter and buffer, in name order (equal digests = identical weights)."""
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def write_rank_audit(directory: Path, rank: int, epoch: int, keys: list[str], digest: str, node_id: str) -> None:
    """``rank-<r>.json``; ``node_id`` is the Ray node the rank ran on, ``pid`` its process on that node."""
    audit = {"rank": rank, "epoch": epoch, "node_id": node_id, "pid": os.getpid(), "weights_sha256": digest,
             "keys": keys}
    write_text(Path(directory) / f"rank-{rank}.json", json.dumps(audit))


def read_rank_audits(directory: Path) -> list[dict[str, Any]]:
    """The ``rank-<r>.json`` audits of one checkpoint folder, by rank."""
    return sorted((json.loads(p.read_text()) for p in Path(directory).glob("rank-*.json")),
                  key=lambda audit: audit["rank"])


def _read_bytes(location: str) -> bytes:
    with fsspec.open(location, "rb") as f:
        return f.read()

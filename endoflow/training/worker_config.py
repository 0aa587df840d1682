"""What the training driver hands every Ray worker: one typed, picklable object (no dicts cross the boundary)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from endoflow.config import Params


@dataclass(frozen=True)
class WorkerConfig:
    """The input of :func:`endoflow.training.loop.train_loop_per_worker`.

    Locations are absolute paths or fsspec URLs (workers run in their own session folders); ``resume_from``
    is the newest complete checkpoint the driver found in storage, or ``None``; ``unlogged_metrics`` is where
    rank 0 keeps the metrics the MLflow store does not take (:func:`endoflow.tracking.unlogged_file`).
    """

    params: Params
    train_shards: tuple[str, ...]
    val_shards: tuple[str, ...]
    latent_bank: Optional[str]
    tracking_uri: str
    run_id: str
    resume_from: Optional[str]
    unlogged_metrics: Optional[str] = None

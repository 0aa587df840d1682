"""What the training driver hands every Ray worker: one typed, picklable object (no dicts cross the boundary)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from endoflow.config import Params


@dataclass(frozen=True)
class WorkerConfig:
    """The input of :func:`endoflow.training.loop.train_loop_per_worker`.

    ``train_shards`` holds the train shards of each folder trained on (``train.shards``, then those of
    ``train.mix``) and ``batch_shares`` how many samples of every batch each gives
    (:func:`endoflow.data.loader.batch_shares`); ``val_shards`` the val shards of all of them. ``learn_intrinsics``
    maps each dataset whose K is unknown in the train shards to the assumed K (``3 x 3`` rows at the stored size)
    of its first such sample: training learns those cameras' intrinsics and logs them from that K.
    Locations are absolute paths or fsspec URLs (workers run in their own session folders); ``resume_from``
    is the newest complete checkpoint the driver found in storage, or ``None``; ``unlogged_metrics`` is where
    rank 0 keeps the metrics the MLflow store does not take (:func:`endoflow.tracking.unlogged_file`).
    """

    params: Params
    train_shards: tuple[tuple[str, ...], ...]
    val_shards: tuple[str, ...]
    latent_bank: Optional[str]
    tracking_uri: str
    run_id: str
    resume_from: Optional[str]
    unlogged_metrics: Optional[str] = None
    batch_shares: tuple[int, ...] = ()
    learn_intrinsics: dict[str, list[list[float]]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.batch_shares) != len(self.train_shards):
            raise ValueError(f"one batch share per train folder: {len(self.train_shards)} folders, "
                             f"shares {self.batch_shares}")

    @property
    def all_train_shards(self) -> tuple[str, ...]:
        return tuple(url for urls in self.train_shards for url in urls)

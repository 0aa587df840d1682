"""Fail fast when the connected Ray cluster cannot hold the training workers.

Ray Train reserves a placement group of ``ray.num_workers`` bundles (``ray.cpus_per_worker`` CPUs, and one GPU
with ``ray.use_gpu``) and waits, silently and without a time limit, until the cluster has room: on a cluster
too small it waits forever. What the cluster has is only known once Ray is connected, so this check runs
then, before the trainer starts; :mod:`endoflow.config` already rejects what it can see at load.

Ray Train's own actor: Ray Train v2 (the default of the installed Ray 2.60) runs its controller actor with no
CPU; Ray Train v1 (older Ray, or ``RAY_TRAIN_V2_ENABLED=0``) reserves one CPU for its trainer actor. The check
compares ``ScalingConfig.total_resources`` of the Ray Train in use, which counts that actor when it needs a CPU.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from endoflow.config import ConfigError, RayConfig

if TYPE_CHECKING:
    from ray.train import ScalingConfig


def scaling_config(cfg: RayConfig) -> ScalingConfig:
    """Ray Train's ``ScalingConfig`` for ``cfg``: ``ray.num_workers`` workers of ``ray.cpus_per_worker`` CPUs,
    and one GPU each with ``ray.use_gpu``."""
    from ray.train import ScalingConfig

    return ScalingConfig(num_workers=cfg.num_workers, use_gpu=cfg.use_gpu,
                         resources_per_worker={"CPU": cfg.cpus_per_worker})


def check_worker_resources(cfg: RayConfig) -> None:
    """Raise :class:`ConfigError` when the connected Ray cluster cannot place every training worker.

    Compares the cluster's total CPUs and GPUs with what ``ray.num_workers`` workers (and Ray Train's own actor)
    need, and each worker's share with the largest live node, since one worker's resources must fit one node.
    Call after ``ray.init`` and before the trainer starts.
    """
    import ray

    need = scaling_config(cfg).total_resources
    have = ray.cluster_resources()
    _check_gpus(cfg, need.get("GPU", 0.0), have.get("GPU", 0.0))
    _check_cpus(cfg, need.get("CPU", 0.0), have.get("CPU", 0.0))
    _check_one_worker_fits_a_node(cfg, [node["Resources"] for node in ray.nodes() if node["Alive"]])


def _check_gpus(cfg: RayConfig, need: float, have: float) -> None:
    if need > have:
        raise ConfigError(
            f"ray.use_gpu is true: ray.num_workers = {cfg.num_workers} workers need {need:g} GPUs (one each), "
            f"the Ray cluster has {have:g}; set ray.use_gpu false or lower ray.num_workers"
        )


def _check_cpus(cfg: RayConfig, need: float, have: float) -> None:
    if need <= have:
        return
    trainer = need - cfg.num_workers * cfg.cpus_per_worker
    trainer_note = f" + {trainer:g} for Ray Train's trainer actor" if trainer else ""
    raise ConfigError(
        f"ray.num_workers x ray.cpus_per_worker = {cfg.num_workers} x {cfg.cpus_per_worker:g}{trainer_note} = "
        f"{need:g} CPUs, the Ray cluster has {have:g}; lower ray.num_workers or ray.cpus_per_worker"
    )


def _check_one_worker_fits_a_node(cfg: RayConfig, nodes: list[dict[str, float]]) -> None:
    gpus = 1.0 if cfg.use_gpu else 0.0
    if any(node.get("CPU", 0.0) >= cfg.cpus_per_worker and node.get("GPU", 0.0) >= gpus for node in nodes):
        return
    largest = max(nodes, key=lambda node: (node.get("CPU", 0.0), node.get("GPU", 0.0)), default={})
    worker = f"ray.cpus_per_worker = {cfg.cpus_per_worker:g} CPUs" + (" and 1 GPU (ray.use_gpu)" if gpus else "")
    raise ConfigError(
        f"{worker} for one worker fit on no node of the Ray cluster (largest: {largest.get('CPU', 0.0):g} CPUs, "
        f"{largest.get('GPU', 0.0):g} GPUs); lower ray.cpus_per_worker"
    )

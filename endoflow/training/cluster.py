"""Fail fast when the connected Ray cluster cannot hold the training workers.

Ray Train waits without a time limit for room for its workers; this check runs once Ray is connected, before the
trainer starts, and names the ``ray.*`` key to change. See docs/cluster.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from endoflow.config import ConfigError, RayConfig

if TYPE_CHECKING:
    from ray.train import ScalingConfig


def scaling_config(cfg: RayConfig) -> ScalingConfig:
    """Ray Train's ``ScalingConfig`` for ``cfg``: ``ray.num_workers`` workers of ``ray.cpus_per_worker`` CPUs,
    and one GPU each with ``ray.use_gpu``, placed by ``ray.placement_strategy``."""
    from ray.train import ScalingConfig

    return ScalingConfig(num_workers=cfg.num_workers, use_gpu=cfg.use_gpu,
                         resources_per_worker={"CPU": cfg.cpus_per_worker},
                         placement_strategy=cfg.placement_strategy)


def check_worker_resources(cfg: RayConfig) -> None:
    """Raise :class:`ConfigError` when the connected Ray cluster cannot place every training worker.

    Compares the cluster's total CPUs and GPUs with what ``ray.num_workers`` workers (and Ray Train's own actor)
    need, and each worker's share with the largest live node, since one worker's resources must fit one node;
    ``ray.placement_strategy`` STRICT_SPREAD needs a node per worker, STRICT_PACK one node for all of them.
    Call after ``ray.init`` and before the trainer starts.
    """
    import ray

    need = scaling_config(cfg).total_resources
    have = ray.cluster_resources()
    nodes = [node["Resources"] for node in ray.nodes() if node["Alive"]]
    _check_gpus(cfg, need.get("GPU", 0.0), have.get("GPU", 0.0))
    _check_cpus(cfg, need.get("CPU", 0.0), have.get("CPU", 0.0))
    _check_one_worker_fits_a_node(cfg, nodes)
    if cfg.placement_strategy == "STRICT_SPREAD":
        _check_a_node_per_worker(cfg, nodes)
    elif cfg.placement_strategy == "STRICT_PACK":
        _check_one_node_fits_every_worker(cfg, nodes)


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


def _fits(node: dict[str, float], cfg: RayConfig, workers: int) -> bool:
    """Whether ``node`` has the CPUs (and GPUs) of ``workers`` workers."""
    gpus = 1.0 if cfg.use_gpu else 0.0
    return node.get("CPU", 0.0) >= workers * cfg.cpus_per_worker and node.get("GPU", 0.0) >= workers * gpus


def _worker_size(cfg: RayConfig) -> str:
    return f"{cfg.cpus_per_worker:g} CPUs" + (" and 1 GPU" if cfg.use_gpu else "")


def _check_one_worker_fits_a_node(cfg: RayConfig, nodes: list[dict[str, float]]) -> None:
    if any(_fits(node, cfg, 1) for node in nodes):
        return
    largest = max(nodes, key=lambda node: (node.get("CPU", 0.0), node.get("GPU", 0.0)), default={})
    gpu = " and 1 GPU (ray.use_gpu)" if cfg.use_gpu else ""
    worker = f"ray.cpus_per_worker = {cfg.cpus_per_worker:g} CPUs{gpu}"
    raise ConfigError(
        f"{worker} for one worker fit on no node of the Ray cluster (largest: {largest.get('CPU', 0.0):g} CPUs, "
        f"{largest.get('GPU', 0.0):g} GPUs); lower ray.cpus_per_worker"
    )


def _check_a_node_per_worker(cfg: RayConfig, nodes: list[dict[str, float]]) -> None:
    fitting = sum(_fits(node, cfg, 1) for node in nodes)
    if fitting < cfg.num_workers:
        raise ConfigError(
            f"ray.placement_strategy STRICT_SPREAD puts each of ray.num_workers = {cfg.num_workers} workers on a "
            f"node of its own, but {fitting} of the {len(nodes)} live nodes of the Ray cluster have room for one "
            f"worker ({_worker_size(cfg)}); lower ray.num_workers, add nodes or choose SPREAD"
        )


def _check_one_node_fits_every_worker(cfg: RayConfig, nodes: list[dict[str, float]]) -> None:
    if not any(_fits(node, cfg, cfg.num_workers) for node in nodes):
        raise ConfigError(
            f"ray.placement_strategy STRICT_PACK puts all ray.num_workers = {cfg.num_workers} workers "
            f"({_worker_size(cfg)} each) on one node, but no live node of the Ray cluster has room for them; lower "
            f"ray.num_workers or choose PACK"
        )

"""Training on a Ray cluster too small for its workers (or for their placement strategy) fails at once, naming the
key, instead of waiting forever."""

from __future__ import annotations


import pytest
import ray

from endoflow.config import ConfigError, RayConfig, params_from_dict
from endoflow.training.cluster import check_worker_resources, scaling_config


@pytest.fixture(scope="module")
def two_cpu_ray():
    """A local Ray with 2 CPUs and no GPU, shared by this module's tests (starting Ray takes seconds)."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("RAY_USAGE_STATS_ENABLED", "0")
        ray.init(address="local", num_cpus=2, num_gpus=0, include_dashboard=False, object_store_memory=80 * 2**20)
        yield
        ray.shutdown()


def test_workers_that_fit_pass(two_cpu_ray):
    check_worker_resources(RayConfig(num_workers=2, cpus_per_worker=1.0))
    check_worker_resources(RayConfig(num_workers=1, cpus_per_worker=2.0))


def test_too_many_workers_name_the_keys_and_the_numbers(two_cpu_ray):
    with pytest.raises(ConfigError, match=r"ray\.num_workers x ray\.cpus_per_worker = 3 x 1 = 3 CPUs, "
                                          r"the Ray cluster has 2"):
        check_worker_resources(RayConfig(num_workers=3, cpus_per_worker=1.0))


def test_workers_too_large_for_the_cluster_name_cpus_per_worker(two_cpu_ray):
    with pytest.raises(ConfigError, match=r"ray\.cpus_per_worker = 1 x 2\.5 = 2\.5 CPUs, the Ray cluster has 2"):
        check_worker_resources(RayConfig(num_workers=1, cpus_per_worker=2.5))


def test_gpu_workers_without_gpus_name_use_gpu(two_cpu_ray):
    with pytest.raises(ConfigError, match=r"ray\.use_gpu is true: ray\.num_workers = 1 workers need 1 GPUs "
                                          r"\(one each\), the Ray cluster has 0"):
        check_worker_resources(RayConfig().replace(use_gpu=True))


def test_a_worker_must_fit_on_one_node(monkeypatch):
    # Two 1-CPU nodes hold 2 CPUs in all, but no node can hold a 2-CPU worker.
    nodes = [{"Alive": True, "Resources": {"CPU": 1.0}}, {"Alive": True, "Resources": {"CPU": 1.0}},
             {"Alive": False, "Resources": {"CPU": 8.0}}]
    monkeypatch.setattr(ray, "cluster_resources", lambda: {"CPU": 2.0})
    monkeypatch.setattr(ray, "nodes", lambda: nodes)
    with pytest.raises(ConfigError, match=r"ray\.cpus_per_worker = 2 CPUs for one worker fit on no node of the "
                                          r"Ray cluster \(largest: 1 CPUs, 0 GPUs\)"):
        check_worker_resources(RayConfig(num_workers=1, cpus_per_worker=2.0))


def fake_cluster(monkeypatch, *cpus_per_node: float) -> None:
    nodes = [{"Alive": True, "Resources": {"CPU": cpus}} for cpus in cpus_per_node]
    monkeypatch.setattr(ray, "cluster_resources", lambda: {"CPU": sum(cpus_per_node)})
    monkeypatch.setattr(ray, "nodes", lambda: nodes)


def test_strict_spread_needs_a_node_per_worker(monkeypatch):
    # Three workers of one CPU fit the 4 CPUs of two nodes, but STRICT_SPREAD wants three nodes.
    fake_cluster(monkeypatch, 2.0, 2.0)
    check_worker_resources(RayConfig(num_workers=3, cpus_per_worker=1.0, placement_strategy="SPREAD"))
    with pytest.raises(ConfigError, match=r"ray\.placement_strategy STRICT_SPREAD puts each of ray\.num_workers = 3 "
                                          r"workers on a node of its own, but 2 of the 2 live nodes"):
        check_worker_resources(RayConfig(num_workers=3, cpus_per_worker=1.0, placement_strategy="STRICT_SPREAD"))
    fake_cluster(monkeypatch, 2.0, 2.0, 0.5)  # a third node too small for a worker does not count
    with pytest.raises(ConfigError, match=r"but 2 of the 3 live nodes .* room for one worker \(1 CPUs\)"):
        check_worker_resources(RayConfig(num_workers=3, cpus_per_worker=1.0, placement_strategy="STRICT_SPREAD"))


def test_strict_pack_needs_one_node_for_every_worker(monkeypatch):
    fake_cluster(monkeypatch, 2.0, 2.0)
    check_worker_resources(RayConfig(num_workers=2, cpus_per_worker=1.0, placement_strategy="STRICT_PACK"))
    with pytest.raises(ConfigError, match=r"ray\.placement_strategy STRICT_PACK puts all ray\.num_workers = 3 "
                                          r"workers \(1 CPUs each\) on one node"):
        check_worker_resources(RayConfig(num_workers=3, cpus_per_worker=1.0, placement_strategy="STRICT_PACK"))


def test_the_placement_strategy_reaches_ray_train():
    assert scaling_config(RayConfig(placement_strategy="STRICT_SPREAD")).placement_strategy == "STRICT_SPREAD"


def test_placement_strategy_and_max_failures_are_checked_at_load():
    with pytest.raises(ConfigError, match=r"ray\.placement_strategy must be one of \['PACK', 'SPREAD', "
                                          r"'STRICT_PACK', 'STRICT_SPREAD'\], got 'spread'"):
        params_from_dict({"ray": {"placement_strategy": "spread"}})
    with pytest.raises(ConfigError, match=r"ray\.max_failures must be >= -1, got -2"):
        params_from_dict({"ray": {"max_failures": -2}})
    assert params_from_dict({"ray": {"max_failures": -1}}).ray.max_failures == -1  # Ray's "no limit"

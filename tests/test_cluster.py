"""Training on a Ray cluster too small for its workers fails at once, naming the key, instead of waiting forever."""

from __future__ import annotations

from dataclasses import replace

import pytest
import ray

from endoflow.config import ConfigError, RayConfig
from endoflow.training.cluster import check_worker_resources


@pytest.fixture(scope="module")
def two_cpu_ray():
    """A local Ray with 2 CPUs and no GPU, shared by this module's tests (starting Ray takes seconds)."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("RAY_USAGE_STATS_ENABLED", "0")
        ray.init(num_cpus=2, num_gpus=0, include_dashboard=False, object_store_memory=80 * 2**20)
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
        check_worker_resources(replace(RayConfig(), use_gpu=True))


def test_a_worker_must_fit_on_one_node(monkeypatch):
    # Two 1-CPU nodes hold 2 CPUs in all, but no node can hold a 2-CPU worker.
    nodes = [{"Alive": True, "Resources": {"CPU": 1.0}}, {"Alive": True, "Resources": {"CPU": 1.0}},
             {"Alive": False, "Resources": {"CPU": 8.0}}]
    monkeypatch.setattr(ray, "cluster_resources", lambda: {"CPU": 2.0})
    monkeypatch.setattr(ray, "nodes", lambda: nodes)
    with pytest.raises(ConfigError, match=r"ray\.cpus_per_worker = 2 CPUs for one worker fit on no node of the "
                                          r"Ray cluster \(largest: 1 CPUs, 0 GPUs\)"):
        check_worker_resources(RayConfig(num_workers=1, cpus_per_worker=2.0))

"""Ray's network exposure, and training on a Ray cluster of several nodes, built on this machine with
``ray.cluster_utils.Cluster``: a head without CPUs and two nodes of one CPU each, so two one-CPU workers can only
run on different nodes. Shards and Ray's storage are ``file://`` URLs, as a shared filesystem would be.

- a local Ray (``ray.address`` null) listens on loopback only;
- ``ray.address`` joins the cluster, ``ray.placement_strategy`` STRICT_SPREAD puts the two workers on the two
  nodes (their node ids are in the rank audits), both hold identical weights after every epoch and trained on
  disjoint samples; every node imports the driver's endoflow, and a driver whose endoflow differs is refused,
  naming each node;
- fault tolerance: with ``ray.max_failures`` 1, the process of one worker (found through epoch 0's rank audit)
  killed during epoch 1: Ray Train restarts both workers from epoch 0's checkpoint and the run finishes by
  itself, epoch 0 neither lost nor repeated, with weights bit-identical to the uninterrupted run's.
"""

from __future__ import annotations

import ipaddress
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
import ray
import torch
from ray.cluster_utils import Cluster

import endoflow
from endoflow.config import Params, RayConfig
from endoflow.ray_runtime import ClusterMismatchError, connect_ray
from endoflow.training.checkpoint import load_training_state, read_rank_audits
from endoflow.training.ray_trainer import train
from tests.module_temp import ModuleTemp
from tests.test_ray import checkpoint_folders, project

pytestmark = pytest.mark.slow

NODE_MEMORY = 80 * 2**20  # object store per node; Ray's minimum is 75 MiB


def test_a_local_ray_listens_on_loopback_only():
    assert not ray.is_initialized()
    before = listening_sockets()
    started = connect_ray(RayConfig(num_cpus=1, object_store_mb=80))
    try:
        assert started
        ray.get(ray.remote(num_cpus=1)(lambda: os.getpid()).remote())  # a worker process is up and listening
        opened = listening_sockets() - before
    finally:
        ray.shutdown()
    names = {name for _, name, _, _ in opened}
    assert {"gcs_server", "raylet"} <= names, names  # the check sees Ray's servers
    assert all(is_loopback(ip) for _, _, ip, _ in opened), sorted(opened)


def listening_sockets() -> set[tuple[int, str, str, int]]:
    """``(pid, process name, ip, port)`` of every listening TCP socket of this process and its descendants."""
    sockets = set()
    for process in [psutil.Process(), *psutil.Process().children(recursive=True)]:
        try:
            sockets |= {(process.pid, process.name(), c.laddr.ip, c.laddr.port)
                        for c in process.net_connections(kind="tcp") if c.status == psutil.CONN_LISTEN}
        except psutil.NoSuchProcess:
            continue
    return sockets


def is_loopback(ip: str) -> bool:
    address = ipaddress.ip_address(ip)
    mapped = getattr(address, "ipv4_mapped", None)  # ::ffff:127.0.0.1 on an IPv6 socket
    return (mapped or address).is_loopback


@pytest.fixture(scope="module")
def cluster():
    """A head with no CPUs (Ray Train's controller needs none) and two nodes of one CPU each."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("RAY_USAGE_STATS_ENABLED", "0")
        nodes = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False,
                                                              "object_store_memory": NODE_MEMORY})
        try:
            for _ in range(2):
                nodes.add_node(num_cpus=1, object_store_memory=NODE_MEMORY)
            yield nodes
        finally:
            nodes.shutdown()


def cluster_params(root: Path, cluster: Cluster) -> Params:
    """Two epochs of two one-CPU workers on ``cluster``, shards and checkpoints at ``file://`` URLs."""
    params = project(root, epochs=2, steps_per_epoch=None)
    params.train.shards = (root / "data" / "shards" / "simcol").as_uri()
    params.ray = params.ray.replace(address=cluster.address, num_workers=2, cpus_per_worker=1.0,
                                    placement_strategy="STRICT_SPREAD",
                                    storage_path=(root / "checkpoints").as_uri())
    return params


@pytest.fixture(scope="module")
def uninterrupted(cluster, module_tmp: ModuleTemp) -> tuple[Path, dict[str, Any]]:
    """The project folder and summary of a training on the cluster that nothing interrupts."""
    root = module_tmp("uninterrupted")
    return root, train(cluster_params(root, cluster), root)


def test_two_workers_run_on_two_nodes_with_identical_weights_and_disjoint_samples(cluster, uninterrupted):
    root, summary = uninterrupted
    assert summary["epochs"] == 2
    folders = checkpoint_folders(root / "checkpoints")
    assert [f.name for f in folders] == ["epoch-0000", "epoch-0001"]
    worker_nodes = {node.node_id for node in cluster.worker_nodes}
    for folder in folders:
        audits = read_rank_audits(folder)
        assert [a["rank"] for a in audits] == [0, 1]
        assert {a["node_id"] for a in audits} == worker_nodes  # one worker on each node
        assert audits[0]["weights_sha256"] == audits[1]["weights_sha256"]
        assert audits[0]["keys"] and not set(audits[0]["keys"]) & set(audits[1]["keys"])


def test_a_driver_with_another_endoflow_is_refused_naming_every_node(cluster, monkeypatch):
    tree_version = endoflow.__version__
    monkeypatch.setattr(endoflow, "__version__", "0.0.0-elsewhere")  # the workers import the tree's version
    with pytest.raises(ClusterMismatchError, match=r"the Ray workers import another endoflow than "
                                                   r"this driver's endoflow 0\.0\.0-elsewhere") as refused:
        connect_ray(RayConfig(address=cluster.address))
    for node in [cluster.head_node, *cluster.worker_nodes]:
        named = f"node {node.node_id[:12]} ({node.node_ip_address}) imports endoflow {tree_version}"
        assert named in str(refused.value)
    assert not ray.is_initialized()  # the refused connection was closed


def test_every_worker_addresses_its_own_cluster_and_only_trainings_import_ray_train(cluster):
    """The worker setup gives each worker its cluster's address: without one, Ray Train's placement-group cleaner
    looked for the machine's only Ray and died with "Found multiple active Ray instances" wherever two ran (two
    runs side by side), printing its traceback into the run's output. The setup leaves Ray Train unimported."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    connect_ray(RayConfig(address=cluster.address))
    try:
        nodes = [node["NodeID"] for node in ray.nodes() if node["Alive"]]
        seen = ray.get([ray.remote(num_cpus=0)(what_a_worker_sees).options(
            scheduling_strategy=NodeAffinitySchedulingStrategy(node, soft=False)).remote() for node in nodes])
        address = ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()
    assert len(nodes) == 3
    assert seen == [(address, False)] * 3


def what_a_worker_sees() -> tuple[str | None, bool]:
    """``RAY_ADDRESS`` in this worker, and whether it imported Ray Train."""
    import sys

    return os.environ.get("RAY_ADDRESS"), "ray.train" in sys.modules


def test_a_worker_killed_during_an_epoch_is_replaced_and_training_finishes_by_itself(cluster, uninterrupted,
                                                                                      tmp_path):
    params = cluster_params(tmp_path, cluster)
    params.ray = params.ray.replace(max_failures=1)
    storage = tmp_path / "checkpoints"
    kill: dict[str, Any] = {}
    training_over = threading.Event()
    killer = threading.Thread(target=kill_rank_1_during_epoch_1, args=(storage, kill, training_over), daemon=True)
    killer.start()

    try:
        summary = train(params, tmp_path)  # returns only if Ray Train recovered by itself
    finally:
        training_over.set()
    killer.join(timeout=10)
    assert "error" not in kill, kill.get("error")
    assert kill["epoch_1_checkpointed"] is False  # the kill came during epoch 1
    folders = checkpoint_folders(storage)
    assert [f.name for f in folders] == ["epoch-0000", "epoch-0001"]
    assert (folders[0] / "state.pt").read_bytes() == kill["epoch_0_state"]  # epoch 0 was not trained again
    replacement = read_rank_audits(folders[1])[1]
    assert replacement["pid"] != kill["pid"]  # a new process trained epoch 1 as rank 1
    resumed = load_training_state(folders[-1])
    assert [record["epoch"] for record in resumed.state.history] == [1, 2]  # counted from 1

    reference_root, reference_summary = uninterrupted
    assert summary["global_steps"] == reference_summary["global_steps"]
    reference = load_training_state(checkpoint_folders(reference_root / "checkpoints")[-1])
    assert resumed.state.history == reference.state.history
    assert all(torch.equal(resumed.model[k], v) for k, v in reference.model.items())


def kill_rank_1_during_epoch_1(storage: Path, kill: dict[str, Any], training_over: threading.Event) -> None:
    """Once Ray Train has recorded epoch 0's checkpoint, SIGKILL rank 1's process (named in epoch 0's rank
    audit); note what the storage held at that moment. Errors go to ``kill["error"]``.

    It waits as long as the training runs rather than for a fixed time: on a loaded machine the two nodes
    take minutes to start, and a fixed wait failed the test without anything being wrong."""
    try:
        while not epoch_0_recorded(storage):
            if training_over.is_set() and not epoch_0_recorded(storage):  # not recorded as the training ended
                raise RuntimeError("the training ended before Ray Train recorded epoch 0's checkpoint; storage "
                                   f"held {sorted(p.relative_to(storage).as_posix() for p in storage.rglob('*'))}")
            time.sleep(0.05)
        epoch_0 = next(storage.glob("endoflow-train-*/epoch-0000"))
        pid = read_rank_audits(epoch_0)[1]["pid"]
        worker = psutil.Process(pid)
        assert worker in psutil.Process().children(recursive=True), "rank 1 is no process of this test's cluster"
        worker.send_signal(signal.SIGKILL)
        kill.update(pid=pid, epoch_1_checkpointed=any(storage.glob("endoflow-train-*/epoch-0001")),
                    epoch_0_state=(epoch_0 / "state.pt").read_bytes())
    except Exception as exc:  # reported by the test, which cannot see a thread's exceptions
        kill["error"] = f"{type(exc).__name__}: {exc}"


def epoch_0_recorded(storage: Path) -> bool:
    """Ray Train's checkpoint manager has recorded epoch 0 (it lists it in the snapshot it keeps beside the
    checkpoints); a worker lost before that would make Ray restart from scratch, and epoch 0 would repeat."""
    return any("epoch-0000" in snapshot.read_text()
               for snapshot in storage.glob("endoflow-train-*/checkpoint_manager_snapshot.json"))

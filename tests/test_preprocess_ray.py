"""Preprocessing on a Ray cluster (``preprocess.engine: ray``): the shards and manifest are the local engine's,
byte for byte, and a damaged source frame fails the run with the file named, from inside the Ray task.

The cluster is two Ray nodes of one CPU each on this machine (``ray.cluster_utils.Cluster``, what
``ray start --head`` and ``ray start --address`` make on real machines); the output is a ``file://`` URL.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import pytest
import ray
import yaml
from ray.cluster_utils import Cluster

from endoflow.config import Params, params_to_dict
from endoflow.data.shard_engines import stop_tasks
from endoflow.data.shards import preprocess_dataset
from endoflow.errors import DataFormatError
from endoflow.io import TEMPORARY_MARK
from tests.fixtures_native import write_simcol
from tests.module_temp import ModuleTemp

pytestmark = pytest.mark.slow

PROJECT = Path(__file__).resolve().parents[1]
NODE = {"num_cpus": 1, "object_store_memory": 80 * 2**20}
# The last frame of the test sequence O1: only the last test shard reads it (as the next frame of O1's last
# target), so every other shard can be finished when the run fails.
DAMAGED_FRAME = ("SyntheticColon_III", "O1", 7)


@pytest.fixture(scope="module")
def cluster() -> Iterator[Cluster]:
    """A head node and a second node, one CPU each, shared by this module's tests (starting them takes ~5 s)."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("RAY_USAGE_STATS_ENABLED", "0")
        cluster = Cluster(initialize_head=True, head_node_args={**NODE, "include_dashboard": False})
        cluster.add_node(**NODE)
        cluster.wait_for_nodes()
        yield cluster
        cluster.shutdown()


@pytest.fixture(scope="module")
def simcol(module_tmp: ModuleTemp) -> tuple[Path, Path]:
    """A SimCol root (S1 train, S4 val, O1 test; 8 frames) and its shards written by the local engine."""
    root = module_tmp("raw") / "simcol"
    write_simcol(root, frames=8, size=40)
    local = module_tmp("local") / "simcol"
    preprocess_dataset("simcol", small_params(root, "local", address=None, out=str(local.parent)), local)
    return root, local


def small_params(root: Path, engine: str, address: str | None, out: str) -> Params:
    """12 shards of 1 or 2 samples (4 per split), 32 px."""
    params = Params()
    params.data.simcol.root = str(root)
    params.data.size = 32
    params.preprocess = params.preprocess.replace(out=out, engine=engine, workers=1, samples_per_shard=2,
                                                  shard_multiple=2)
    params.train = params.train.replace(batch_size=2)  # data.size 32 needs two samples per batch
    params.ray = params.ray.replace(address=address)
    return params


def same_files(a: Path, b: Path) -> dict[str, bool]:
    """Per file name in either folder: whether both hold it with the same bytes."""
    names = sorted({p.name for p in a.iterdir()} | {p.name for p in b.iterdir()})
    return {name: (a / name).is_file() and (b / name).is_file()
            and (a / name).read_bytes() == (b / name).read_bytes() for name in names}


def test_the_stage_on_a_cluster_writes_the_local_engines_bytes_to_a_file_url(
    cluster: Cluster, simcol: tuple[Path, Path], tmp_path: Path
) -> None:
    root, local = simcol
    params_file = tmp_path / "params.yaml"
    params = small_params(root, "ray", address=cluster.address, out=(tmp_path / "shards").as_uri())
    params_file.write_text(yaml.safe_dump(params_to_dict(params)))
    # The timeout guards against a hang only: the stage took 14 s alone and more than 120 s beside two other test
    # processes on 2 cores, where Ray's processes wait for the cores like everything else.
    run = subprocess.run([sys.executable, "-m", "stages.preprocess", "simcol", "--params", str(params_file)],
                         cwd=PROJECT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert cluster.address in run.stderr  # the driver joined the cluster rather than starting a Ray of its own
    progress = [line for line in run.stdout.splitlines() if line.startswith("[preprocess] simcol: ")]
    assert progress[-1].startswith("[preprocess] simcol: 12/12 shards |") and "done in" in progress[-1]
    summary = run.stdout.splitlines()[-2:]  # a summary a person reads, not a JSON dump
    assert re.fullmatch(r"\[preprocess\] simcol done: train \d+ samples in 4 shards, val \d+ samples in 4 shards, "
                        r"test \d+ samples in 4 shards; 0 shards kept .*frames/s\)", summary[0]), summary
    assert summary[1] == f"[preprocess] written to {(tmp_path / 'shards').as_uri()}/simcol"
    files = same_files(local, tmp_path / "shards" / "simcol")
    assert len(files) == 13 and all(files.values()), files  # 12 shards and the manifest
    assert [p.name for p in (tmp_path / "shards").iterdir()] == ["simcol"]  # no staging folder left


def test_a_damaged_frame_fails_naming_the_file_and_a_rerun_keeps_the_finished_shards(
    cluster: Cluster, simcol: tuple[Path, Path], tmp_path: Path
) -> None:
    root, local = simcol
    scene, name, number = DAMAGED_FRAME
    frame = root / scene / f"Frames_{name}" / f"FrameBuffer_{number:04d}.png"
    intact = frame.read_bytes()
    out = (tmp_path / "shards").as_uri()
    params = small_params(root, "ray", address=cluster.address, out=out)
    frame.write_bytes(intact[: len(intact) // 2])
    try:
        with pytest.raises(DataFormatError, match=frame.name):
            preprocess_dataset("simcol", params, f"{out}/simcol")
    finally:
        frame.write_bytes(intact)
    assert not (tmp_path / "shards" / "simcol").exists()
    staged = {p.name for p in (tmp_path / "shards" / ".simcol.partial").iterdir()}
    assert not [name for name in staged if TEMPORARY_MARK in name], staged  # no task still writing
    finished = {name for name in staged if name.endswith(".tar")}
    assert finished and "test-000003.tar" not in finished
    summary = preprocess_dataset("simcol", params, f"{out}/simcol")
    assert summary["shards_reused"] == len(finished)
    assert all(same_files(local, tmp_path / "shards" / "simcol").values())


def test_stopping_after_an_error_returns_only_when_every_running_task_has_ended(
    cluster: Cluster, tmp_path: Path
) -> None:
    def write_after_a_while(path: str) -> None:
        Path(f"{path}.started").write_text("started")
        try:
            time.sleep(3)
        finally:
            Path(path).write_text("ended")

    ray.init(address=cluster.address, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1)(write_after_a_while)
        markers = [tmp_path / f"task-{index}" for index in range(2)]
        pending = [task.remote(str(marker)) for marker in markers]
        # both running, one per node: a loaded machine takes a while to start a worker (in a CI run of the whole
        # suite one had not started after 60 s, and a task cancelled before it starts rightly writes nothing)
        deadline = time.monotonic() + 300
        while not all(Path(f"{marker}.started").exists() for marker in markers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert all(Path(f"{marker}.started").exists() for marker in markers), "a task did not start within 300 s"
        stop_tasks(pending)
        assert all(marker.exists() for marker in markers)
    finally:
        ray.shutdown()

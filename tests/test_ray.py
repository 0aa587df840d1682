"""Training on Ray Train with DDP, on tiny shards (64 px, one or two steps per epoch).

Starting Ray costs about 10 s on two cores and a training's workers as much again, so each test combines several
checks, and the trainings in this process share one local Ray (a training joins a running Ray and leaves it
running; the stage killed below starts its own, as `dvc repro` does):

- two CPU workers, killed after the first epoch's checkpoint and run again: the rerun continues with the
  next epoch (the finished epoch is neither lost nor repeated) and ends with weights bit-identical to an
  uninterrupted run's (every rank's random state is restored), both ranks hold identical weights after
  every epoch and trained on disjoint samples, the storage path may be a ``file://`` URL, and the MLflow run
  (reopened by the rerun) holds params, losses, validation metrics, depth images and the model; the
  uninterrupted run keeps only ``train.keep_checkpoints`` checkpoints;
- a learning rate that turns NaN after the first epoch (shards read through a ``file://`` URL): training
  stops with an error naming the epoch and step, the first epoch's checkpoint stays, no model file is
  written and the MLflow run is marked failed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Iterator

import pytest
import torch
import yaml

from endoflow import tracking
from endoflow.config import Params, RayConfig, params_to_dict
from endoflow.data.shards import write_dataset_shards
from endoflow.io import file_sha256
from endoflow.models.mlflow_model import using_store
from endoflow.models.model_file import load_model_file
from endoflow.ray_runtime import connect_ray
from endoflow.training.checkpoint import latest_checkpoint, load_training_state, read_rank_audits, weights_digest
from endoflow.training.ray_trainer import TrainingError, train, training_fingerprint
from tests.test_evaluate import OracleSource, shard_params


def project(tmp_path: Path, **train_overrides) -> Params:
    """A project folder with shards and params for a tiny training (no latent bank)."""
    params = shard_params(tmp_path / "data" / "shards")
    write_dataset_shards(OracleSource(), "simcol", params, tmp_path / "data" / "shards" / "simcol")
    params.model = params.model.replace(latent_bank=False)
    tiny = {"batch_size": 2, "steps_per_epoch": 1, "val_batches": 1, "log_every": 1, "image_examples": 1}
    params.train = params.train.replace(**{**tiny, **train_overrides})
    # one CPU a worker, so that two fit this machine's two; an error ends the run at once
    params.ray = params.ray.replace(num_workers=1, num_cpus=2, cpus_per_worker=1.0, max_failures=0)
    return params


@pytest.fixture(scope="module")
def shared_ray() -> Iterator[Callable[[], None]]:
    """Call it to have a local Ray of two CPUs running in this process; it is shut down after the module."""
    import ray

    def start() -> None:
        connect_ray(RayConfig(num_cpus=2))

    yield start
    ray.shutdown()


def checkpoint_folders(storage: Path) -> list[Path]:
    return sorted(storage.glob("endoflow-train-*/epoch-*"))


def first_checkpoint_complete(storage: Path) -> bool:
    """Ray has finished copying epoch 0: a complete ``state.pt`` and both ranks' audits."""
    runs = list(storage.glob("endoflow-train-*"))
    return bool(runs) and latest_checkpoint(str(runs[0]), ranks=2) is not None and len(
        list(runs[0].glob("epoch-0000/rank-*.json"))) == 2


def run_stage_until_first_checkpoint(root: Path, storage: Path, timeout: float = 600) -> None:
    """Run the training stage as dvc.yaml does (``python -m stages.train``, the project on the path) in ``root``,
    in its own process group, and kill it all once epoch 0 is checkpointed. The limit is there to end a hung stage,
    not to time a slow one (on a loaded machine a fixed 300 s wait of this kind failed the two-node test), and
    within the test's own timeout (pyproject.toml), so that its message is the one shown."""
    project = Path(__file__).resolve().parents[1]
    process = subprocess.Popen([sys.executable, "-m", "stages.train"], cwd=root, start_new_session=True,
                               env={**os.environ, "PYTHONPATH": str(project)},
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + timeout
        while not first_checkpoint_complete(storage):
            assert process.poll() is None, "the training stage exited before its first checkpoint"
            assert time.monotonic() < deadline, (f"the training stage, still running, checkpointed no epoch "
                                                 f"in {timeout:.0f} s")
            time.sleep(0.2)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()


@pytest.mark.slow
def test_two_workers_killed_and_rerun_resume_with_identical_weights_and_disjoint_samples(tmp_path: Path,
                                                                                        shared_ray):
    params = project(tmp_path, epochs=2)
    storage = tmp_path / "checkpoints"
    params.ray = params.ray.replace(num_workers=2, storage_path=storage.as_uri())  # an fsspec URL
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params_to_dict(params)))

    run_stage_until_first_checkpoint(tmp_path, storage)
    assert [f.name for f in checkpoint_folders(storage)] == ["epoch-0000"]
    first_epoch = (checkpoint_folders(storage)[0] / "state.pt").read_bytes()

    shared_ray()
    summary = train(params, tmp_path)

    folders = checkpoint_folders(storage)
    assert [f.name for f in folders] == ["epoch-0000", "epoch-0001"]
    assert (folders[0] / "state.pt").read_bytes() == first_epoch  # epoch 0 was not trained again
    assert summary["epochs"] == 2 and summary["global_steps"] == 2
    for folder in folders:
        audits = read_rank_audits(folder)
        assert [a["rank"] for a in audits] == [0, 1]
        assert audits[0]["weights_sha256"] == audits[1]["weights_sha256"]
        assert audits[0]["keys"] and not set(audits[0]["keys"]) & set(audits[1]["keys"])

    record = load_model_file(tmp_path / params.train.out)
    assert record.epoch == summary["best_epoch"] and record.baselines.mean_depth_map.shape == (64, 64)
    assert (tmp_path / params.train.metrics).is_file()
    assert (tmp_path / params.train.plots / "curves.png").is_file()

    uri = tracking.tracking_uri(params, tmp_path)
    runs = tracking.client(uri).search_runs([tracking.ensure_experiment(params, tmp_path, "endoflow")])
    assert [r.info.run_id for r in runs] == [summary["mlflow_run_id"]]  # the rerun reopened the run
    run = runs[0]
    assert run.info.status == "FINISHED"
    assert run.data.params["ray.num_workers"] == "2"
    (train_shards,) = run.inputs.dataset_inputs  # logged by both runs, kept once
    assert train_shards.dataset.digest == file_sha256(tmp_path / params.train.shards / "manifest.parquet")[:32]
    history = tracking.client(uri).get_metric_history(run.info.run_id, "val_abs_rel")
    epochs = tracking.client(uri).get_metric_history(run.info.run_id, "epoch")
    # Both epochs are logged at their last global step (one step each), on the per-step metrics' axis, with the
    # epoch (from 1) beside them; the killed run's workers may have logged epoch 2 too before they died (they run
    # in Ray's own process groups, so the kill reaches them a moment later), which MLflow keeps as a second value.
    assert sorted({m.step for m in history}) == [1, 2]
    assert sorted({(m.step, m.value) for m in epochs}) == [(1, 1.0), (2, 2.0)]
    assert {"loss/total", "loss/weighted/kl", "loss/unweighted/kl", "loss/weighted/photometric"} <= set(
        run.data.metrics)
    with using_store(uri):  # MLflow resolves the run's logged model ("model/") through the process-wide store
        artifacts = {a.path for folder in ("val_depth", "model", "logs")
                     for a in tracking.client(uri).list_artifacts(run.info.run_id, folder)}
    assert {"val_depth/epoch_0001.png", "val_depth/epoch_0002.png", "val_depth/latest.png",
            "model/MLmodel"} <= artifacts  # the model, as an MLflow model (tests/test_mlflow_model.py)
    assert "logs/ray-from-epoch-0002.log" in artifacts  # what Ray printed in the rerun (the killed run had no time)
    (tmp_path / "downloaded").mkdir()
    ray_log = Path(tracking.client(uri).download_artifacts(run.info.run_id, "logs/ray-from-epoch-0002.log",
                                                          str(tmp_path / "downloaded")))
    assert "RayTrainWorker" in ray_log.read_text()  # the workers' lines...
    assert "PreemptionWatcher" not in ray_log.read_text()  # ...and none from a watcher, which a local Ray does not run

    # the same training, never interrupted, keeping one checkpoint: the same weights, bit for bit
    reference = tmp_path / "uninterrupted"
    reference_params = project(reference, epochs=2, keep_checkpoints=1)
    reference_params.ray = params.ray.replace(storage_path=str(reference / "checkpoints"))
    train(reference_params, reference)
    assert [f.name for f in checkpoint_folders(reference / "checkpoints")] == ["epoch-0001"]
    resumed = load_training_state(folders[-1])
    uninterrupted = load_training_state(checkpoint_folders(reference / "checkpoints")[-1])
    assert resumed.state.history == uninterrupted.state.history
    assert all(torch.equal(resumed.model[k], v) for k, v in uninterrupted.model.items())


@pytest.mark.slow
def test_a_non_finite_loss_stops_training_naming_the_step_and_keeps_the_last_checkpoint(tmp_path: Path, shared_ray):
    # the learning rate becomes NaN after epoch 0, so the first update of epoch 1 breaks the weights (a copy
    # without validation: a params file with a NaN gamma is refused at load)
    params = project(tmp_path, epochs=3, steps_per_epoch=2, schedule="step", step_epochs=1)
    params.train = params.train.model_copy(update={"gamma": float("nan")})
    params.ray = params.ray.replace(storage_path=str(tmp_path / "checkpoints"))
    params.train.shards = (tmp_path / "data" / "shards" / "simcol").as_uri()  # shards through fsspec

    shared_ray()
    with pytest.raises(TrainingError, match=r"NonFiniteLossError: non-finite training loss .* at epoch 1, step 1"):
        train(params, tmp_path)

    assert [f.name for f in checkpoint_folders(tmp_path / "checkpoints")] == ["epoch-0000"]
    assert not (tmp_path / params.train.out).exists()
    uri = tracking.tracking_uri(params, tmp_path)
    runs = tracking.client(uri).search_runs([tracking.ensure_experiment(params, tmp_path, "endoflow")])
    assert [r.info.status for r in runs] == ["FAILED"]


def test_weights_digest_tells_models_apart():
    first, second = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    second.load_state_dict(first.state_dict())
    assert weights_digest(first) == weights_digest(second)
    with torch.no_grad():
        second.bias.add_(1e-6)
    assert weights_digest(first) != weights_digest(second)


def test_resume_picks_the_newest_complete_checkpoint_also_through_a_url(tmp_path: Path):
    run = tmp_path / "endoflow-train-abc"
    for epoch in range(4):
        folder = run / f"epoch-{epoch:04d}"
        folder.mkdir(parents=True)
        torch.save({"epoch": epoch}, folder / "state.pt")
        for rank in range(2):
            torch.save({"rank": rank}, folder / f"rng-rank-{rank}.pt")
    data = (run / "epoch-0003" / "state.pt").read_bytes()
    (run / "epoch-0003" / "state.pt").write_bytes(data[: len(data) // 2])  # killed while copying
    (run / "epoch-0002" / "rng-rank-1.pt").unlink()  # killed before rank 1's files arrived
    assert latest_checkpoint(str(run), ranks=2) == str(run / "epoch-0001")
    assert latest_checkpoint(run.as_uri(), ranks=2) == (run / "epoch-0001").as_uri()
    assert latest_checkpoint(str(run), ranks=1) == str(run / "epoch-0002")
    assert latest_checkpoint(str(tmp_path / "never-ran"), ranks=1) is None


def test_fingerprint_ignores_the_epoch_count_but_not_what_training_computes(tmp_path: Path):
    (tmp_path / "manifest.parquet").write_bytes(b"manifest")
    params = Params()
    base = training_fingerprint(params, str(tmp_path), None)
    params.train = params.train.replace(epochs=params.train.epochs + 5, log_every=1)
    assert training_fingerprint(params, str(tmp_path), None) == base  # more epochs continue the run
    # later stages, and how the shards were written (their bytes are the manifest's): the run resumes
    params.reconstruct = params.reconstruct.replace(voxel_cm=0.05, device="cpu")
    params.eval = params.eval.replace(batch_size=3)
    params.preprocess = params.preprocess.replace(workers=7, engine="ray")
    params.data.endoslam = params.data.endoslam.replace(fps=25.0)
    assert training_fingerprint(params, str(tmp_path), None) == base
    params.train = params.train.replace(lr=params.train.lr * 2)
    assert training_fingerprint(params, str(tmp_path), None) != base
    (tmp_path / "manifest.parquet").write_bytes(b"other data")
    params.train = params.train.replace(lr=params.train.lr / 2)
    assert training_fingerprint(params, str(tmp_path), None) != base


def test_a_local_rays_workers_import_the_drivers_endoflow_not_the_installed_one(tmp_path: Path):
    """A queued DVC experiment runs its stages in a copy of the project: the workers must train with the copy's
    code, not with the installed (editable) package the workspace holds, which may have changed since."""
    import shutil

    project = Path(__file__).resolve().parents[1]
    copy = tmp_path / "copy"
    shutil.copytree(project / "endoflow", copy / "endoflow", ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "endoflow" / "only_in_the_copy.py").write_text("WHERE = 'the copy'\n")
    script = (
        "import ray\n"
        "from endoflow.config import RayConfig\n"
        "from endoflow.ray_runtime import connect_ray\n"
        "connect_ray(RayConfig(num_cpus=1))\n"
        "def where():\n"
        "    from endoflow.only_in_the_copy import WHERE\n"
        "    return WHERE\n"
        "print(ray.get(ray.remote(num_cpus=1)(where).remote()))\n"
    )
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    run = subprocess.run([sys.executable, "-c", script], cwd=copy, capture_output=True, text=True, timeout=300,
                         env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.strip().splitlines()[-1] == "the copy"

"""MLflow helpers: the embedded store lives at the project root, runs carry flat params and reopen on resume."""

from __future__ import annotations

import hashlib
import json
import os
import socket
import subprocess
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402
from mlflow.entities import RunStatus  # noqa: E402

from endoflow import tracking  # noqa: E402
from endoflow.config import Params  # noqa: E402
from endoflow.locations import home_project  # noqa: E402


def test_default_store_is_an_absolute_sqlite_file_with_artifacts_beside_it(tmp_path: Path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    params = Params()
    assert tracking.tracking_uri(params, ".") == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    assert tracking.artifact_location(params, ".") == (tmp_path.resolve() / "mlartifacts").as_uri()
    params.tracking.uri = "http://mlflow.example:5000"
    assert tracking.tracking_uri(params, ".") == "http://mlflow.example:5000"
    assert tracking.artifact_location(params, ".") is None


def test_flat_params_reach_into_nested_sections_and_test_sets():
    flat = tracking.flat_params(Params())
    assert flat["model.latent_bank"] == "True"
    assert flat["train.lr"] == "0.0002"  # the default (params.yaml)
    assert flat["eval.test_sets.simcol_3.groups"] == "['SyntheticColon_III']"
    assert all(isinstance(v, str) for v in flat.values())


def test_run_has_params_commit_metrics_artifacts_and_reopens_while_unfinished(tmp_path: Path):
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty",
                    "-m", "init"], cwd=tmp_path, check=True)
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    opened = tracking.start_run(params, tmp_path, "exp", "train", fingerprint="abc")
    run_id = opened.run_id
    opened.log_metrics({"loss/total": 1.5, "val abs_rel(paper)": 0.2}, step=3)
    figure = plt.figure()
    opened.log_figure(figure, "val_depth/epoch_000.png")
    plt.close(figure)

    # an interrupted training resumed with the same inputs logs into the same run
    with tracking.run(params, tmp_path, "exp", "train", fingerprint="abc") as resumed:
        assert resumed == opened
        assert tracking.start_run(params, tmp_path, "exp", "train", fingerprint="other") != opened
    assert tracking.start_run(params, tmp_path, "exp", "train", fingerprint="abc") != opened

    run = tracking.client(uri).get_run(run_id)
    assert run.data.params["model.pose_vae"] == "True"
    assert run.data.tags[tracking.GIT_COMMIT_TAG].startswith(
        subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, capture_output=True, text=True).stdout.strip())
    assert run.data.metrics == {"loss/total": 1.5, "val abs_rel_paper_": 0.2}
    assert run.info.status == "FINISHED"
    assert (tmp_path / "mlflow.db").is_file()
    assert (tmp_path / "mlartifacts").is_dir()
    assert list((tmp_path / "mlartifacts").rglob("epoch_000.png"))


def test_a_run_ends_finished_failed_on_an_error_or_killed_on_an_interrupt_and_the_unfinished_reopen(
        tmp_path: Path):
    params = Params()
    with tracking.run(params, tmp_path, "exp", "done", fingerprint="d") as done:
        done.log_metrics({"loss/total": 1.0})
    with pytest.raises(ValueError, match="the training's own error"):
        with tracking.run(params, tmp_path, "exp", "failed", fingerprint="f") as failed:
            raise ValueError("the training's own error")
    with pytest.raises(KeyboardInterrupt):
        with tracking.run(params, tmp_path, "exp", "interrupted", fingerprint="i") as interrupted:
            raise KeyboardInterrupt

    mlflow_client = tracking.client(tracking.tracking_uri(params, tmp_path))
    status = {run.run_id: mlflow_client.get_run(run.run_id).info.status for run in (done, failed, interrupted)}
    assert status == {done.run_id: "FINISHED", failed.run_id: "FAILED", interrupted.run_id: "KILLED"}
    # a rerun with the same inputs goes on in the unfinished runs
    assert tracking.start_run(params, tmp_path, "exp", "failed", fingerprint="f") == failed
    assert tracking.start_run(params, tmp_path, "exp", "interrupted", fingerprint="i") == interrupted
    assert tracking.start_run(params, tmp_path, "exp", "done", fingerprint="d") != done


def test_experiments_are_model_training_experiments_with_a_description(tmp_path: Path):
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    training = tracking.client(uri).get_experiment(tracking.ensure_experiment(params, tmp_path, "endoflow"))
    bank = tracking.client(uri).get_experiment(
        tracking.ensure_experiment(params, tmp_path, params.tracking.latent_bank_experiment))
    for experiment in (training, bank):
        assert experiment.tags[tracking.EXPERIMENT_KIND_TAG] == tracking.MODEL_TRAINING_KIND
    assert "depth and pose training" in training.tags[tracking.DESCRIPTION_TAG]
    assert "latent bank" in bank.tags[tracking.DESCRIPTION_TAG]


def test_an_older_experiment_without_a_kind_gets_one(tmp_path: Path):
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    old = tracking.client(uri).create_experiment("endoflow")
    assert tracking.ensure_experiment(params, tmp_path, "endoflow") == old
    assert tracking.client(uri).get_experiment(old).tags[tracking.EXPERIMENT_KIND_TAG] == tracking.MODEL_TRAINING_KIND


def test_runs_are_named_after_their_dvc_experiment_else_what_distinguishes_them(monkeypatch):
    params = Params()
    params.model.pose_vae = False
    params.seed = 3
    monkeypatch.delenv(tracking.DVC_EXPERIMENT_ENV, raising=False)
    name = tracking.run_name_for("train", [*tracking.ablation_switches(params), f"seed{params.seed}"])
    assert name == "train bank no-vae seed3"
    monkeypatch.setenv(tracking.DVC_EXPERIMENT_ENV, "no-vae")
    assert tracking.run_name_for("train", ["anything"]) == "no-vae"


def test_a_run_carries_its_source_its_dvc_experiment_and_its_latent_bank_run(tmp_path: Path, monkeypatch):
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    monkeypatch.setenv(tracking.DVC_EXPERIMENT_ENV, "no-vae")
    monkeypatch.setattr("sys.argv", [str(tmp_path / "stages" / "train.py")])
    bank_run = tracking.start_run(params, tmp_path, params.tracking.latent_bank_experiment, "bank")
    bank_run.set_tags({tracking.LATENT_BANK_DIGEST_TAG: "d1"})
    run = tracking.start_run(params, tmp_path, "endoflow", "no-vae")
    assert tracking.link_latent_bank(params, run, "d1") == bank_run.run_id
    tags = tracking.client(uri).get_run(run.run_id).data.tags
    assert tags[tracking.SOURCE_NAME_TAG] == "stages/train.py" and tags[tracking.SOURCE_TYPE_TAG] == "LOCAL"
    assert tags[tracking.DVC_EXPERIMENT_TAG] == "no-vae"
    assert tags[tracking.LATENT_BANK_RUN_TAG] == bank_run.run_id and tags[tracking.LATENT_BANK_DIGEST_TAG] == "d1"
    # a bank this store never pretrained (copied from elsewhere): its digest only
    other = tracking.start_run(params, tmp_path, "endoflow", "other")
    assert tracking.link_latent_bank(params, other, "d2") is None
    assert tracking.LATENT_BANK_RUN_TAG not in tracking.client(uri).get_run(other.run_id).data.tags


def test_a_shard_folder_is_a_dataset_input_named_by_its_manifest_and_digest_once_per_run(tmp_path: Path):
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    manifest = tmp_path / "shards" / "simcol" / "manifest.parquet"
    manifest.parent.mkdir(parents=True)
    manifest.write_bytes(b"the manifest's bytes")
    run = tracking.start_run(params, tmp_path, "endoflow", "train")
    digest = run.log_shards_input(str(manifest), "simcol", "training")
    run.log_shards_input(str(manifest), "simcol", "training")  # a resumed run logs it again
    assert digest == hashlib.sha256(b"the manifest's bytes").hexdigest()[:32]
    (logged,) = tracking.client(uri).get_run(run.run_id).inputs.dataset_inputs
    assert (logged.dataset.name, logged.dataset.digest, logged.dataset.source_type) == ("simcol", digest, "local")
    assert json.loads(logged.dataset.source) == {"uri": str(manifest)}
    assert {tag.key: tag.value for tag in logged.tags} == {"mlflow.data.context": "training"}
    # changed shards are another input (another digest)
    manifest.write_bytes(b"other bytes")
    run.log_shards_input(manifest.as_uri(), "simcol", "evaluation")
    inputs = tracking.client(uri).get_run(run.run_id).inputs.dataset_inputs
    assert sorted((i.dataset.source_type, i.tags[0].value) for i in inputs) == [("file", "evaluation"),
                                                                               ("local", "training")]


def test_a_queued_dvc_experiment_uses_the_store_of_the_project_it_was_queued_in(tmp_path: Path, monkeypatch):
    """DVC runs a queued experiment in a temporary copy, which it deletes after; DVC_ROOT names the project."""
    project, copy = tmp_path / "project", tmp_path / "project" / ".dvc" / "tmp" / "exps" / "run" / "abc"
    copy.mkdir(parents=True)
    params = Params()
    assert tracking.tracking_uri(params, copy) == f"sqlite:///{copy / 'mlflow.db'}"
    monkeypatch.setenv("DVC_ROOT", str(project))
    assert tracking.tracking_uri(params, copy) == f"sqlite:///{project / 'mlflow.db'}"
    assert tracking.artifact_location(params, copy) == (project / "mlartifacts").as_uri()
    assert home_project(copy) == project


# ---------------------------------------------------------------------------------- a lost tracking server
def closed_port() -> int:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def lost_server_uri(monkeypatch) -> str:
    """The URI of a tracking server that is gone, with MLflow's retries and timeout set small."""
    monkeypatch.setattr(tracking, "_lost_stores", {})
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "2")
    return f"http://127.0.0.1:{closed_port()}"


@pytest.fixture
def lost_server(monkeypatch) -> str:
    return lost_server_uri(monkeypatch)


def unlogged_entries(file: Path) -> list[dict]:
    return [json.loads(line) for line in file.read_text().splitlines()]


def test_a_lost_server_warns_once_keeps_the_metrics_and_the_end_and_never_raises(
        lost_server: str, tmp_path: Path, capsys) -> None:
    kept = tmp_path / "project" / tracking.UNLOGGED_FOLDER / "run1.jsonl"
    run = tracking.RunHandle.attach(lost_server, "run1", kept)  # as a Ray worker attaches to the driver's run
    picture = tmp_path / "curves.png"
    picture.write_bytes(b"\x89PNG\r\n\x1a\n")
    started = time.monotonic()

    for step in range(5):
        run.log_metrics({"loss/total": 0.5 + step}, step=step)
    run.log_artifact(picture, "plots/train")
    run.set_tags({tracking.LATENT_BANK_DIGEST_TAG: "ab"})
    run.end(RunStatus.FAILED)

    assert time.monotonic() - started < 10
    warnings = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(warnings) == 1 and lost_server in warnings[0] and str(kept) in warnings[0]
    entries = unlogged_entries(kept)
    assert [(e["step"], e["metrics"]) for e in entries[:-1]] == [(s, {"loss/total": 0.5 + s}) for s in range(5)]
    assert entries[-1]["status"] == "FAILED"


def test_metrics_kept_while_the_server_was_lost_are_replayed_into_the_run(lost_server: str, tmp_path: Path) -> None:
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    run = tracking.start_run(params, tmp_path, "exp", "train")
    run_id = run.run_id
    run.log_metrics({"loss/total": 3.0}, step=0)
    lost = tracking.RunHandle.attach(lost_server, run_id)  # the server is lost: the same run, seen through it
    for step in (1, 2):
        lost.log_metrics({"loss/total": 3.0 - step}, step=step)
    lost.end()
    kept = tracking.project_unlogged_file(tmp_path, run_id)

    assert tracking.replay_unlogged(uri, kept) == 3
    history = tracking.client(uri).get_metric_history(run_id, "loss/total")
    assert sorted((m.step, m.value) for m in history) == [(0, 3.0), (1, 2.0), (2, 1.0)]
    assert tracking.client(uri).get_run(run_id).info.status == "FINISHED"
    assert not kept.exists()
    with pytest.raises(FileNotFoundError):  # a local file's error is no lost store: it is raised as it is
        run.log_artifact(tmp_path / "missing.png")


def test_requests_give_up_after_seconds_unless_the_environment_says_otherwise(monkeypatch) -> None:
    for name in tracking.QUICK_HTTP_SETTINGS:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "300")
    tracking.client("http://127.0.0.1:1")  # no request is made
    assert os.environ["MLFLOW_HTTP_REQUEST_MAX_RETRIES"] == "2"  # MLflow's 7 retried for about 4 minutes
    assert os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] == "300"


def test_runs_left_running_by_a_killed_process_of_this_machine_are_marked_killed_at_the_next_start(
        tmp_path: Path) -> None:
    from tests.test_atomic_writes import ended_process_mark

    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    mlflow_client = tracking.client(uri)
    killed = tracking.start_run(params, tmp_path, "latent-bank", "latent-bank seed0").run_id
    elsewhere = tracking.start_run(params, tmp_path, "latent-bank", "latent-bank seed1").run_id
    mlflow_client.set_tag(killed, tracking.PROCESS_TAG, ended_process_mark())  # killed before its run ended
    mlflow_client.set_tag(elsewhere, tracking.PROCESS_TAG, ended_process_mark().split("@")[0] + "@another-host")
    still_running = tracking.start_run(params, tmp_path, "latent-bank", "latent-bank seed2").run_id  # this process

    again = tracking.start_run(params, tmp_path, "latent-bank", "latent-bank seed0").run_id

    status = {run_id: mlflow_client.get_run(run_id).info.status for run_id in (killed, elsewhere, still_running, again)}
    assert status == {killed: "KILLED", elsewhere: "RUNNING", still_running: "RUNNING", again: "RUNNING"}

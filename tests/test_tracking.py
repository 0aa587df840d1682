"""MLflow helpers: the embedded store lives at the project root, runs carry flat params and reopen on resume."""

from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

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
    assert flat["train.lr"] == "0.0001"
    assert flat["eval.test_sets.simcol_3.groups"] == "['SyntheticColon_III']"
    assert all(isinstance(v, str) for v in flat.values())


def test_run_has_params_commit_metrics_artifacts_and_reopens_while_unfinished(tmp_path: Path):
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty",
                    "-m", "init"], cwd=tmp_path, check=True)
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    run_id = tracking.start_run(params, tmp_path, "exp", "train", fingerprint="abc")
    tracking.log_metrics(uri, run_id, {"loss/total": 1.5, "val abs_rel(paper)": 0.2}, step=3)
    figure = plt.figure()
    tracking.log_figure(uri, run_id, figure, "val_depth/epoch_000.png")
    plt.close(figure)

    # an interrupted training resumed with the same inputs logs into the same run
    assert tracking.start_run(params, tmp_path, "exp", "train", fingerprint="abc") == run_id
    assert tracking.start_run(params, tmp_path, "exp", "train", fingerprint="other") != run_id
    tracking.end_run(uri, run_id)
    assert tracking.start_run(params, tmp_path, "exp", "train", fingerprint="abc") != run_id

    run = tracking.client(uri).get_run(run_id)
    assert run.data.params["model.pose_vae"] == "True"
    assert run.data.tags[tracking.GIT_COMMIT_TAG].startswith(
        subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, capture_output=True, text=True).stdout.strip())
    assert run.data.metrics == {"loss/total": 1.5, "val abs_rel_paper_": 0.2}
    assert run.info.status == "FINISHED"
    assert (tmp_path / "mlflow.db").is_file()
    assert (tmp_path / "mlartifacts").is_dir()
    assert list((tmp_path / "mlartifacts").rglob("epoch_000.png"))


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
    tracking.set_tags(uri, bank_run, {tracking.LATENT_BANK_DIGEST_TAG: "d1"})
    run_id = tracking.start_run(params, tmp_path, "endoflow", "no-vae")
    assert tracking.link_latent_bank(params, tmp_path, run_id, "d1") == bank_run
    tags = tracking.client(uri).get_run(run_id).data.tags
    assert tags[tracking.SOURCE_NAME_TAG] == "stages/train.py" and tags[tracking.SOURCE_TYPE_TAG] == "LOCAL"
    assert tags[tracking.DVC_EXPERIMENT_TAG] == "no-vae"
    assert tags[tracking.LATENT_BANK_RUN_TAG] == bank_run and tags[tracking.LATENT_BANK_DIGEST_TAG] == "d1"
    # a bank this store never pretrained (copied from elsewhere): its digest only
    other = tracking.start_run(params, tmp_path, "endoflow", "other")
    assert tracking.link_latent_bank(params, tmp_path, other, "d2") is None
    assert tracking.LATENT_BANK_RUN_TAG not in tracking.client(uri).get_run(other).data.tags


def test_a_shard_folder_is_a_dataset_input_named_by_its_manifest_and_digest_once_per_run(tmp_path: Path):
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    manifest = tmp_path / "shards" / "simcol" / "manifest.parquet"
    manifest.parent.mkdir(parents=True)
    manifest.write_bytes(b"the manifest's bytes")
    run_id = tracking.start_run(params, tmp_path, "endoflow", "train")
    digest = tracking.log_shards_input(uri, run_id, str(manifest), "simcol", "training")
    tracking.log_shards_input(uri, run_id, str(manifest), "simcol", "training")  # a resumed run logs it again
    assert digest == hashlib.sha256(b"the manifest's bytes").hexdigest()[:32]
    (logged,) = tracking.client(uri).get_run(run_id).inputs.dataset_inputs
    assert (logged.dataset.name, logged.dataset.digest, logged.dataset.source_type) == ("simcol", digest, "local")
    assert json.loads(logged.dataset.source) == {"uri": str(manifest)}
    assert {tag.key: tag.value for tag in logged.tags} == {"mlflow.data.context": "training"}
    # changed shards are another input (another digest)
    manifest.write_bytes(b"other bytes")
    tracking.log_shards_input(uri, run_id, manifest.as_uri(), "simcol", "evaluation")
    inputs = tracking.client(uri).get_run(run_id).inputs.dataset_inputs
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

"""The whole pipeline, as a user runs it: the smoke preset through `dvc repro` in a fresh copy of the project.

One run (a few minutes on 2 cores) is shared by every assertion below, so the module keeps its state in a
module-scoped fixture.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mlflow import MlflowClient

from endoflow.config import load_params
from tests.project_clone import PROJECT, clone_project, pipeline_env, run


pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def smoke_repro(tmp_path_factory) -> Path:
    clone = tmp_path_factory.mktemp("e2e") / "endoflow"
    env = pipeline_env("e2e")
    clone_project(clone, (PROJECT / "presets" / "smoke.yaml").read_text(), env)
    run(["dvc", "repro"], clone, env)
    return clone


def test_every_stage_output_exists(smoke_repro):
    params = load_params(smoke_repro / "params.yaml")
    for dataset in ("simcol", "endoslam", "scenenet"):
        shards = smoke_repro / params.preprocess.out / dataset
        assert (shards / "manifest.parquet").is_file()
        assert list(shards.glob("*.tar"))
    for path in (params.latent_bank.out, params.train.out, params.latent_bank.metrics, params.train.metrics):
        assert (smoke_repro / path).is_file(), path
    assert list((smoke_repro / params.latent_bank.plots).glob("*.png"))
    for test_set in params.eval.test_sets:
        assert (smoke_repro / "metrics" / "eval" / f"{test_set}.json").is_file()
        assert any((smoke_repro / "predictions" / test_set).rglob("*.npy"))
    for name in params.reconstruct.sequences:
        for output in ("mesh.ply", "sheet.png", "video.mp4", "trajectory.tum", "reconstruction.json"):
            assert (smoke_repro / params.reconstruct.out / name / output).is_file(), (name, output)
        measured = json.loads((smoke_repro / params.reconstruct.metrics / f"{name}.json").read_text())
        assert set(measured["surface"]) >= {"ground_truth", "model", "trivial"}, name
        assert (smoke_repro / params.reconstruct.plots / name / "sheet.png").is_file()


def test_dvc_metrics_show_lists_training_and_evaluation(smoke_repro):
    env = pipeline_env("e2e")
    shown = json.loads(run(["dvc", "metrics", "show", "--json"], smoke_repro, env).stdout)
    files = {name for workspace in shown.values() for name in workspace.get("data", {})}
    params = load_params(smoke_repro / "params.yaml")
    assert params.train.metrics in files
    assert params.latent_bank.metrics in files
    assert any(name.startswith("metrics/eval/") for name in files)
    assert any(name.startswith(f"{params.reconstruct.metrics}/") for name in files)


def test_one_mlflow_run_holds_training_and_evaluation(smoke_repro):
    params = load_params(smoke_repro / "params.yaml")
    client = MlflowClient(tracking_uri=f"sqlite:///{smoke_repro / 'mlflow.db'}")
    experiment = client.get_experiment_by_name(params.tracking.experiment)
    runs = client.search_runs([experiment.experiment_id])
    assert len(runs) == 1, "one `dvc repro` is one training run"
    run_data = runs[0].data
    assert run_data.params["model.latent_bank"] == str(params.model.latent_bank)
    metric_names = set(run_data.metrics)
    assert any(name.startswith("val_") for name in metric_names), metric_names
    assert any(name.startswith("loss/") for name in metric_names), metric_names
    for test_set in params.eval.test_sets:
        assert any(name.startswith(f"eval/{test_set}/") for name in metric_names), test_set
    artifacts = {item.path for item in client.list_artifacts(runs[0].info.run_id)}
    assert {"model", "eval", "reconstruct"} <= artifacts, artifacts
    assert any(name.startswith("reconstruct/") for name in metric_names), metric_names
    bank = client.get_experiment_by_name(params.tracking.latent_bank_experiment)
    assert len(client.search_runs([bank.experiment_id])) == 1

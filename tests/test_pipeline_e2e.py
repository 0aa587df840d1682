"""The whole pipeline, as a user runs it: the smoke preset through `dvc repro` in a fresh copy of the project.

One run (a few minutes on 2 cores) is shared by every assertion below, so the module keeps its state in a
module-scoped fixture.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mlflow import MlflowClient

from endoflow import tracking
from endoflow.config import load_params
from endoflow.evaluation.results import evaluation_path
from endoflow.io import file_sha256
from endoflow.models.depth_range import COLLAPSED_SHARE
from endoflow.params_file import params_yaml
from tests.module_temp import ModuleTemp
from tests.project_clone import PROJECT, clone_project, pipeline_env, run


pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def smoke_repro(module_tmp: ModuleTemp) -> Path:
    clone = module_tmp("e2e") / "endoflow"
    env = pipeline_env("e2e")
    clone_project(clone, params_yaml(load_params(PROJECT / "presets" / "smoke.yaml")), env)
    run(["dvc", "repro"], clone, env)
    return clone


def test_every_stage_output_exists(smoke_repro):
    params = load_params(smoke_repro / "params.yaml")
    for dataset in ("simcol", "endoslam", "scenenet", "video"):
        shards = smoke_repro / params.preprocess.out / dataset
        assert (shards / "manifest.parquet").is_file()
        assert list(shards.glob("*.tar"))
    for path in (params.latent_bank.out, params.train.out, params.latent_bank.metrics, params.train.metrics):
        assert (smoke_repro / path).is_file(), path
    assert list((smoke_repro / params.latent_bank.plots).glob("*.png"))
    for test_set in params.eval.test_sets:
        assert (smoke_repro / "metrics" / "eval" / f"{test_set}.json").is_file()
        assert any((smoke_repro / "predictions" / test_set).rglob("*.npy"))
        assert evaluation_path(smoke_repro / params.eval.predictions, test_set).is_file()
    for name in params.reconstruct.sequences:
        for output in ("mesh.ply", "sheet.png", "video.mp4", "trajectory.tum", "reconstruction.json"):
            assert (smoke_repro / params.reconstruct.out / name / output).is_file(), (name, output)
        measured = json.loads((smoke_repro / params.reconstruct.out / name / "measurement.json").read_text())
        assert set(measured["surface"]) >= {"ground_truth", "model", "trivial"}, name
        assert (smoke_repro / params.reconstruct.plots / name / "sheet.png").is_file()


def test_the_smoke_run_trained_on_the_built_in_video_beside_simcol(smoke_repro):
    """The smoke preset mixes the unlabelled video into every batch: its shards say they have no ground truth, and
    the training run logged both folders as its inputs."""
    from endoflow.data.loader import list_shards, raw_samples
    from endoflow.data.shard_format import decode_meta, has_ground_truth

    params = load_params(smoke_repro / "params.yaml")
    assert params.train.mix == {"data/shards/video": 1.0}
    urls = list_shards(str(smoke_repro / params.preprocess.out / "video"), "train")
    meta = decode_meta(next(raw_samples(urls))["meta.json"], urls[0])
    assert not has_ground_truth(meta, "depth") and not has_ground_truth(meta, "pose")
    client = MlflowClient(tracking_uri=f"sqlite:///{smoke_repro / 'mlflow.db'}")
    (training,) = client.search_runs([client.get_experiment_by_name(params.tracking.experiment).experiment_id])
    assert {d.dataset.name for d in training.inputs.dataset_inputs} >= {"simcol", "video"}
    assert "val_photometric" in training.data.metrics
    assert training.data.metrics["val_depth_at_range_ends"] < COLLAPSED_SHARE  # the depth did not collapse


def test_dvc_metrics_show_lists_training_and_evaluation(smoke_repro):
    env = pipeline_env("e2e")
    shown = json.loads(run(["dvc", "metrics", "show", "--json"], smoke_repro, env).stdout)
    files = {name for workspace in shown.values() for name in workspace.get("data", {})}
    params = load_params(smoke_repro / "params.yaml")
    assert params.train.metrics in files
    assert params.latent_bank.metrics in files
    assert any(name.startswith("metrics/eval/") for name in files)
    assert any(name.startswith(f"{params.reconstruct.metrics}/") for name in files)


def test_dvc_metrics_are_a_short_numeric_summary(smoke_repro):
    env = pipeline_env("e2e")
    shown = json.loads(run(["dvc", "metrics", "show", "--json"], smoke_repro, env).stdout)
    params = load_params(smoke_repro / "params.yaml")
    values = {}
    for workspace in shown.values():
        for path, content in workspace["data"].items():
            assert "error" not in content, (path, content)
            values.update(flatten(content["data"]))
    assert all(isinstance(value, (int, float)) for value in values.values()), values
    expected = {f"test_{test_set}.{key}" for test_set in params.eval.test_sets
                for key in ("abs_rel", "rte_cm", "rot_deg")}
    expected |= {f"reconstruct_{name}.{key}" for name in params.reconstruct.sequences
                 for key in ("ate_cm", "completeness_2vox_pct")}
    # a mesh's accuracy where it has vertices: the smoke model's depth may leave no cube of the fusion observed on
    # all its corners across the surface; a figure that does not exist is written as null (never NaN), which
    # `dvc metrics show` leaves out
    expected |= {f"reconstruct_{name}.accuracy_cm" for name in params.reconstruct.sequences
                 if json.loads((smoke_repro / params.reconstruct.out / name / "reconstruction.json").read_text()
                               )["mesh"]["vertices"]}
    expected |= {"train.best_epoch", "train.val_abs_rel", "train.val_rmse_cm", "train.val_photometric",
                 "latent_bank.swd_final", "latent_bank.swd_ratio"}
    assert set(values) == expected


def flatten(tree: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def test_dvc_plots_chart_the_declared_columns_and_the_page_works_offline(smoke_repro, tmp_path: Path):
    env = pipeline_env("e2e")
    shown = json.loads(run(["dvc", "plots", "show", "--json"], smoke_repro, env).stdout)
    assert not shown.get("errors"), shown.get("errors")
    charts = {name: entries for name, entries in shown["data"].items() if not name.endswith(".png")}
    # the training curves, two charts per test set, one per reconstructed sequence; all with data
    params = load_params(smoke_repro / "params.yaml")
    assert len(charts) == 1 + 2 * len(params.eval.test_sets) + len(params.reconstruct.sequences), sorted(charts)
    for name, entries in charts.items():
        for entry in entries:
            assert entry["content"]["data"]["values"], name
    pictures = [name for name in shown["data"] if name.endswith(".png")]
    assert any("curves.png" in name for name in pictures) and any("sheet.png" in name for name in pictures)
    run(["dvc", "plots", "show", "-o", str(tmp_path / "page")], smoke_repro, env)
    page = (tmp_path / "page" / "index.html").read_text()
    assert "cannot be drawn" in page and "vegaEmbed" in page


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
        assert any(name.startswith(f"test/{test_set}/") for name in metric_names), test_set
    # one-off figures are tables and files, not one-point charts above the curves
    assert not [name for name in metric_names if name.startswith(("best/", "eval/"))], metric_names
    artifacts = {item.path for item in client.list_artifacts(runs[0].info.run_id)}
    assert {"eval", "reconstruct", "val_depth"} <= artifacts, artifacts
    # the model is an MLflow "logged model" of the run (MLflow 3 keeps its files beside the run's own)
    logged = client.search_logged_models(experiment_ids=[experiment.experiment_id])
    assert [model.source_run_id for model in logged] == [runs[0].info.run_id]
    assert any(name.startswith("reconstruct/") for name in metric_names), metric_names
    bank = client.get_experiment_by_name(params.tracking.latent_bank_experiment)
    bank_runs = client.search_runs([bank.experiment_id])
    assert len(bank_runs) == 1


def test_mlflow_shows_named_model_training_runs_with_their_source_and_headline(smoke_repro):
    params = load_params(smoke_repro / "params.yaml")
    store = f"sqlite:///{smoke_repro / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=store, registry_uri=store)
    experiment = client.get_experiment_by_name(params.tracking.experiment)
    assert experiment.tags[tracking.EXPERIMENT_KIND_TAG] == "custom_model_development"
    assert experiment.tags[tracking.DESCRIPTION_TAG]
    train_run = client.search_runs([experiment.experiment_id])[0]
    assert train_run.info.run_name == f"train bank vae seed{params.seed}"
    assert train_run.data.tags[tracking.SOURCE_NAME_TAG] == "stages/train.py"
    assert train_run.data.tags[tracking.SOURCE_TYPE_TAG] == "LOCAL"
    for test_set in params.eval.test_sets:
        assert {f"test/{test_set}/{key}" for key in ("abs_rel", "rte_cm", "rot_deg")} <= set(train_run.data.metrics)
    bank = client.get_experiment_by_name(params.tracking.latent_bank_experiment)
    bank_run = client.search_runs([bank.experiment_id])[0]
    assert bank.tags[tracking.EXPERIMENT_KIND_TAG] == "custom_model_development"
    assert train_run.data.tags[tracking.LATENT_BANK_RUN_TAG] == bank_run.info.run_id
    assert bank_run.data.tags[tracking.LATENT_BANK_DIGEST_TAG] == file_sha256(smoke_repro / params.latent_bank.out)
    # the smoke preset registers its model: version 1 of tracking.registered_model, from the training run
    version = client.get_model_version(params.tracking.registered_model, "1")
    assert version.run_id == train_run.info.run_id

"""The trained model as an MLflow model: logged with a signature and an input example, registered, loadable
with `mlflow.pyfunc` on its own (depth and camera path of consecutive frames, as the torch model gives them),
nothing pickled; endoflow reads a `models:/` URI's model file back without running the logged code, and
`endoflow reconstruct` takes the URI."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from endoflow import tracking
from endoflow.cli import main as cli
from endoflow.config import Params
from endoflow.geometry.pose import invert_pose
from endoflow.io import file_sha256
from endoflow.models.endoflow_model import build_model, load_trained_model
from endoflow.models.mlflow_model import (PROGRESS_BAR_ENV, example_frames, local_model_file, log_mlflow_model,
                                          using_store)
from endoflow.models.model_file import ModelRecord, TrainingBaselines, save_model_file
from endoflow.reconstruction.measure import stage_model_file
from tests.module_temp import ModuleTemp
from tests.small_model import small_model_params

SIZE = 64
NAME = "endoflow-test"


@pytest.fixture(scope="module")
def project(module_tmp: ModuleTemp) -> Path:
    return module_tmp("mlflow_model_project")


@pytest.fixture(scope="module")
def params() -> Params:
    return small_model_params(SIZE)


@pytest.fixture(scope="module")
def logged(project: Path, params: Params) -> tuple[Path, str, str]:
    """(model file, run id, models:/ URI) of an untrained model logged into a run and registered."""
    model_path = project / "models" / "endoflow.pt"
    model_path.parent.mkdir()
    torch.manual_seed(0)
    model = build_model(params, latent_bank_path=None)
    baselines = TrainingBaselines(mean_depth_cm=7.0, mean_depth_map=np.full((SIZE, SIZE), 7.0, np.float32),
                                  mean_relative_pose=np.eye(4))
    with tracking.run(params, project, params.tracking.experiment, "train bank vae seed0") as run:
        save_model_file(model_path, ModelRecord(params=params, state=model.state_dict(), epoch=0, val={},
                                                mlflow_run_id=run.run_id, baselines=baselines))
        model_uri = log_mlflow_model(run.uri, run.run_id, model_path, NAME)
    return model_path, run.run_id, model_uri


def test_logging_the_model_prints_no_library_notes_and_draws_bars_only_where_the_environment_asks(
        logged, params, tmp_path, monkeypatch, capfd):
    model_path, _, _ = logged
    monkeypatch.delenv(PROGRESS_BAR_ENV, raising=False)  # `make test` sets it, as `make repro` does
    capfd.readouterr()
    with tracking.run(params, tmp_path, params.tracking.experiment, "quiet") as run:
        log_mlflow_model(run.uri, run.run_id, model_path, None)
    err = capfd.readouterr().err
    assert "Downloading artifacts" not in err
    assert " INFO mlflow" not in err  # "Validating input example against model signature"
    assert PROGRESS_BAR_ENV not in os.environ  # left as it was

    monkeypatch.setenv(PROGRESS_BAR_ENV, "true")
    with tracking.run(params, tmp_path, params.tracking.experiment, "asked for bars") as run:
        log_mlflow_model(run.uri, run.run_id, model_path, None)
    assert "Downloading artifacts" in capfd.readouterr().err


def downloaded_model(params: Params, project: Path, destination: Path) -> Path:
    import mlflow

    with using_store(tracking.tracking_uri(params, project)):
        return Path(mlflow.artifacts.download_artifacts(artifact_uri=f"models:/{NAME}/1", dst_path=str(destination)))


def test_the_model_is_registered_with_a_signature_an_input_example_and_no_pickle(logged, params, project,
                                                                                  tmp_path):
    _, run_id, _ = logged
    uri = tracking.tracking_uri(params, project)
    version = tracking.client(uri).get_model_version(NAME, "1")
    assert version.run_id == run_id
    folder = downloaded_model(params, project, tmp_path)
    description = yaml.safe_load((folder / "MLmodel").read_text())
    inputs = json.loads(description["signature"]["inputs"])
    outputs = json.loads(description["signature"]["outputs"])
    assert inputs == [{"type": "tensor", "tensor-spec": {"dtype": "uint8", "shape": [-1, SIZE, SIZE, 3]}}]
    assert [o["name"] for o in outputs] == ["depth_cm", "T_world_cam"]
    assert description["saved_input_example_info"]
    assert not list(folder.rglob("*.pkl")) and not list(folder.rglob("*.pickle"))  # models from code


def test_pyfunc_gives_the_torch_models_depth_and_chained_path(logged, params, project, tmp_path):
    import mlflow

    model_path, _, _ = logged
    with using_store(tracking.tracking_uri(params, project)):
        pyfunc = mlflow.pyfunc.load_model(f"models:/{NAME}/1")
    frames = np.concatenate([example_frames(SIZE), example_frames(SIZE)[:1, :, ::-1]])
    out = pyfunc.predict(frames)
    model, _ = load_trained_model(model_path, torch.device("cpu"))
    images = torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 255
    with torch.no_grad():
        depth = model.predict_depth(images)[:, 0].numpy()
        steps = model.predict_pose(images[:-1], images[1:]).double().numpy()
    assert out["depth_cm"].shape == (3, SIZE, SIZE) and out["depth_cm"].dtype == np.float32
    np.testing.assert_allclose(out["depth_cm"], depth, rtol=1e-5)
    poses = out["T_world_cam"]
    np.testing.assert_allclose(poses[0], np.eye(4))
    np.testing.assert_allclose(poses[1], invert_pose(steps[0]), atol=1e-5)  # T_world_cur = inv(T_cur_prev)
    np.testing.assert_allclose(poses[2], poses[1] @ invert_pose(steps[1]), atol=1e-5)


def test_logging_and_reading_leave_mlflows_process_wide_store_alone(logged, params, project):
    import mlflow

    assert tracking.tracking_uri(params, project) not in (mlflow.get_tracking_uri(), mlflow.get_registry_uri())


def test_endoflow_reads_a_models_uri_as_its_model_file(logged, params, project):
    model_path, _, model_uri = logged
    uri = tracking.tracking_uri(params, project)
    for location in (f"models:/{NAME}/1", model_uri):
        with local_model_file(location, uri) as path:
            assert file_sha256(path) == file_sha256(model_path)
            kept = path
        assert not kept.exists()  # downloaded for the duration only
    with local_model_file(model_path, uri) as path:
        assert path == model_path
    with pytest.raises(FileNotFoundError, match="models:/no-such-model/1: no such model in sqlite:///"):
        with local_model_file("models:/no-such-model/1", uri):
            pass


def test_reconstruct_takes_a_models_uri(logged, params, project, monkeypatch):
    frames = project / "frames"
    frames.mkdir()
    import cv2

    for i, frame in enumerate(np.concatenate([example_frames(SIZE)] * 2)):
        cv2.imwrite(str(frames / f"{i:04d}.png"), frame[:, :, ::-1])
    monkeypatch.chdir(project)
    code = cli(["reconstruct", str(frames), "--model", f"models:/{NAME}/1", "--intrinsics", "50,50,32,32",
                "--out", str(project / "out"), "--no-fusion"])
    assert code == 0
    summary = json.loads((project / "out" / "reconstruction.json").read_text())
    assert summary["frames"] == 4


def test_the_reconstruct_stage_takes_a_models_uri(logged, params, project):
    model_path, _, _ = logged
    stage = params.replace(reconstruct=params.reconstruct.replace(model=f"models:/{NAME}/1"))
    with stage_model_file(stage, project) as path:
        assert file_sha256(path) == file_sha256(model_path)
    relative = params.replace(reconstruct=params.reconstruct.replace(model="models/endoflow.pt"))
    with stage_model_file(relative, project) as path:
        assert path == model_path


def test_evaluate_takes_a_models_uri_and_logs_into_the_models_training_run(logged, params, project):
    from endoflow.data.shards import write_dataset_shards
    from endoflow.evaluation.evaluate import run_evaluation
    from tests.test_evaluate import OracleSource, shard_params

    _, run_id, _ = logged
    shards = project / "eval_shards"
    write_dataset_shards(OracleSource(), "simcol", shard_params(shards), shards / "simcol")
    eval_params = small_model_params(SIZE)
    eval_params.eval = eval_params.eval.replace(shards=str(shards), model=f"models:/{NAME}/1", batch_size=4)
    result = run_evaluation(eval_params, "simcol_3", project)
    assert result["mlflow_run_id"] == run_id and result["frames"] > 0
    assert json.loads((project / eval_params.eval.metrics / "simcol_3.json").read_text())["test_simcol_3"][
        "abs_rel"] == result["depth_paper"]["model"]["abs_rel"]
    logged_metrics = tracking.client(tracking.tracking_uri(eval_params, project)).get_run(run_id).data.metrics
    assert logged_metrics["test/simcol_3/abs_rel"] == pytest.approx(result["depth_paper"]["model"]["abs_rel"])


def test_model_export_takes_a_models_uri(logged, params, project, monkeypatch, capsys):
    from endoflow.models import export

    model_path, _, _ = logged
    seen = {}

    def export_onnx(path, out, model_label=None):  # the export itself is tested in test_export.py
        seen.update(sha256=file_sha256(path), label=model_label)
        return "the report"

    monkeypatch.setattr(export, "export_onnx", export_onnx)
    monkeypatch.setattr(export, "format_export", lambda report: f"printed {report}")
    monkeypatch.chdir(project)
    assert cli(["model", "export", "--model", f"models:/{NAME}/1", "--out", str(project / "onnx")]) == 0
    assert seen == {"sha256": file_sha256(model_path), "label": f"models:/{NAME}/1"}
    assert "printed the report" in capsys.readouterr().out


@pytest.mark.parametrize("artifact", ["../outside.pt", "/tmp/outside.pt", "linked/outside.pt"])
def test_an_mlmodel_naming_a_file_outside_the_downloaded_model_is_refused(tmp_path, artifact):
    from endoflow.errors import DataFormatError
    from endoflow.models.mlflow_model import MODEL_FILE_ARTIFACT, model_file_of

    model_dir = tmp_path / "download"
    model_dir.mkdir()
    (tmp_path / "outside.pt").write_bytes(b"not yours")
    (model_dir / "linked").symlink_to(tmp_path)
    (model_dir / "MLmodel").write_text(yaml.safe_dump(
        {"flavors": {"python_function": {"artifacts": {MODEL_FILE_ARTIFACT: {"path": artifact}}}}}))
    with pytest.raises(DataFormatError, match=rf"models:/m/1: its MLmodel names the model file '{artifact}', outside "
                                              r"the downloaded model: refused"):
        model_file_of(model_dir, "models:/m/1")

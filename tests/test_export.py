"""ONNX export: both graphs reproduce the torch model at any batch size, export.json documents them, and
the command line refuses what it cannot export.

One small model (the latent bank included, 64x64 images) is exported once, through the command line, for
the whole module: exporting takes seconds.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
from pathlib import Path

import numpy as np
import onnxruntime
import pytest
import torch

from endoflow.cli import main as cli_main
from endoflow.config import Params
from endoflow.models import export
from endoflow.models.endoflow_model import build_model, load_trained_model
from endoflow.models.export import ExportVerificationError, export_onnx, verify_graph
from endoflow.models.model_file import ModelRecord, TrainingBaselines, save_model_file
from tests.module_temp import ModuleTemp

SIZE = 64  # the smallest size the depth network accepts (its deepest features are 2x2)
# The untrained pose head predicts almost the identity; this bias (x 0.01 in the network) makes the mean
# motion 0.1 rad and 2 cm, so the axis-angle -> matrix part of the graph is really exercised.
POSE_BIAS = torch.tensor([10.0, -5.0, 8.0, 100.0, -50.0, 200.0])
# Likewise the untrained disparity sits near 0.5 (depth ~0.2 cm); this bias moves it to a few cm, where
# disparity -> depth amplifies differences more.
DISP_BIAS = -4.0
MEASURED: dict[str, float] = {}  # max abs differences, printed at the end (docs/export.md quotes them)


def small_params() -> Params:
    params = Params()
    params.data.size = SIZE
    cfg = params.latent_bank
    cfg.resolution, cfg.start_resolution, cfg.latent_dim, cfg.style_dim = 32, 4, 16, 16
    cfg.mapping_layers, cfg.channel_base, cfg.channel_max = 2, 128, 32
    return params


@pytest.fixture(scope="module")
def model_file(module_tmp: ModuleTemp) -> Path:
    torch.manual_seed(0)
    params = small_params()
    model = build_model(params, latent_bank_path=None)
    with torch.no_grad():
        model.pose_net.mean_head.bias.copy_(POSE_BIAS)
        model.depth_net.decoder.dispconvs[0].bias.fill_(DISP_BIAS)
    path = module_tmp("model") / "endoflow.pt"
    save_model_file(path, ModelRecord(params=params, state=model.state_dict(), epoch=3, val={"val_abs_rel": 0.5},
                                      mlflow_run_id="run-1",
                                      baselines=TrainingBaselines(5.0, np.ones((SIZE, SIZE), np.float32), np.eye(4))))
    return path


@pytest.fixture(scope="module")
def exported(model_file: Path, module_tmp: ModuleTemp) -> tuple[Path, str]:
    """The folder the CLI exported to, and what it printed."""
    out = module_tmp("export") / "onnx"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = cli_main(["model", "export", "--model", str(model_file), "--format", "onnx", "--out", str(out)])
    assert code == 0
    return out, printed.getvalue()


@pytest.fixture(scope="module")
def torch_model(model_file: Path) -> torch.nn.Module:
    return load_trained_model(model_file, torch.device("cpu"))[0]


def images(batch: int, seed: int) -> torch.Tensor:
    return torch.rand(batch, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(seed))


@pytest.fixture(scope="module")
def sessions(exported) -> dict[str, onnxruntime.InferenceSession]:
    """An onnxruntime session (CPU) per exported graph, by file name."""
    return {file: onnxruntime.InferenceSession(str(exported[0] / file), providers=["CPUExecutionProvider"])
            for file in ("depth_net.onnx", "pose_net.onnx")}


def run_onnx(session: onnxruntime.InferenceSession, **inputs: torch.Tensor) -> np.ndarray:
    return session.run(None, {name: value.numpy() for name, value in inputs.items()})[0]


@pytest.fixture(scope="module", autouse=True)
def print_measured():
    yield
    print("\nmax |onnxruntime - torch|:", json.dumps(MEASURED))


def test_the_command_writes_two_graphs_and_export_json_and_prints_sizes_and_differences(exported):
    out, printed = exported
    assert sorted(p.name for p in out.iterdir()) == ["depth_net.onnx", "export.json", "pose_net.onnx"]
    record = json.loads((out / "export.json").read_text())
    for name in ("depth_net", "pose_net"):
        graph = record["graphs"][name]
        size_mib = f"{(out / graph['file']).stat().st_size / 2**20:.1f} MiB"
        line = next(line for line in printed.splitlines() if graph["file"] in line)
        assert size_mib in line and f"{graph['max_abs_diff']:.3g}" in line


@pytest.mark.parametrize("batch", [1, 3])
def test_the_depth_graph_returns_predict_depth_in_cm_at_any_batch_size(sessions, torch_model, batch):
    rgb = images(batch, seed=10 + batch)
    got = run_onnx(sessions["depth_net.onnx"], rgb=rgb)
    with torch.no_grad():
        expected = torch_model.predict_depth(rgb).numpy()
    assert got.shape == (batch, 1, SIZE, SIZE) and got.dtype == np.float32
    cfg = torch_model.cfg
    assert cfg.min_depth <= got.min() and got.max() <= cfg.max_depth
    MEASURED[f"depth_cm, batch {batch}"] = diff = float(np.abs(got - expected).max())
    assert diff <= export.DEPTH_RTOL * max(1.0, float(np.abs(expected).max()))


@pytest.mark.parametrize("batch", [1, 3])
def test_the_pose_graph_returns_the_mean_T_source_target_of_the_next_frame_at_any_batch_size(
        sessions, torch_model, batch):
    target, source = images(batch, seed=20 + batch), images(batch, seed=30 + batch)
    got = run_onnx(sessions["pose_net.onnx"], target=target, source=source)
    expected = torch_model.predict_pose(target, source, source_is_next=True).numpy()
    assert got.shape == (batch, 4, 4) and got.dtype == np.float32
    # really a motion (the bias above), rigid, and the same as torch's mean
    assert np.abs(got[:, :3, 3]).max() > 1.0
    rotation = got[:, :3, :3]
    np.testing.assert_allclose(rotation @ rotation.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (batch, 3, 3)),
                               atol=1e-5)
    np.testing.assert_array_equal(got[:, 3], np.broadcast_to([0, 0, 0, 1], (batch, 4)))
    MEASURED[f"T_source_target, batch {batch}"] = diff = float(np.abs(got - expected).max())
    assert diff <= export.POSE_RTOL * max(1.0, float(np.abs(expected).max()))


def test_every_input_and_output_has_a_dynamic_batch_dimension_and_the_training_size(sessions):
    for file, names in (("depth_net.onnx", ["rgb", "depth_cm"]),
                        ("pose_net.onnx", ["target", "source", "T_source_target"])):
        session = sessions[file]
        args = {a.name: a.shape for a in [*session.get_inputs(), *session.get_outputs()]}
        assert list(args) == names
        assert all(isinstance(shape[0], str) for shape in args.values())  # a symbolic dimension, not a number
        assert all(shape[-2:] in ([SIZE, SIZE], [4, 4]) for shape in args.values())


def test_export_json_names_shapes_units_opset_model_hash_and_the_measured_differences(exported, model_file):
    out = exported[0]
    record = json.loads((out / "export.json").read_text())
    assert record["opset"] == export.OPSET and record["image_size"] == [SIZE, SIZE]
    assert record["model"]["sha256"] == hashlib.sha256(model_file.read_bytes()).hexdigest()
    assert record["model"]["epoch"] == 3 and record["model"]["mlflow_run_id"] == "run-1"
    depth, pose = record["graphs"]["depth_net"], record["graphs"]["pose_net"]
    assert [i["name"] for i in depth["inputs"]] == ["rgb"] and depth["inputs"][0]["shape"] == ["batch", 3, SIZE, SIZE]
    assert depth["outputs"] == [{"name": "depth_cm", "dtype": "float32", "shape": ["batch", 1, SIZE, SIZE],
                                 "unit": "cm", "range": [0.1, 20.0], "meaning": depth["outputs"][0]["meaning"]}]
    assert [i["name"] for i in pose["inputs"]] == ["target", "source"]
    assert pose["outputs"][0]["name"] == "T_source_target" and pose["outputs"][0]["shape"] == ["batch", 4, 4]
    assert "cm" in pose["outputs"][0]["unit"] and "OpenCV" in record["conventions"]["camera"]
    for graph in (depth, pose):
        assert graph["sha256"] == hashlib.sha256((out / graph["file"]).read_bytes()).hexdigest()
        assert 0.0 <= graph["max_abs_diff"] <= graph["tolerance"]
    assert record["verification"]["batch"] == 2 and "CPUExecutionProvider" in record["verification"]["runtime"]


def test_verification_fails_naming_the_graph_when_onnxruntime_and_torch_disagree(exported, torch_model):
    rgb = images(2, seed=5)
    with torch.no_grad():
        expected = torch_model.predict_depth(rgb).numpy()
    path = exported[0] / "depth_net.onnx"  # passed this check at export time, against the exact output
    with pytest.raises(ExportVerificationError, match="depth_net.onnx: onnxruntime differs from torch"):
        verify_graph(path, {"rgb": rgb.numpy()}, expected * 1.01, export.DEPTH_RTOL)


def test_a_graph_that_fails_verification_replaces_nothing_and_leaves_no_temporary(model_file, tmp_path, monkeypatch):
    out = tmp_path / "onnx"
    out.mkdir()
    (out / "depth_net.onnx").write_bytes(b"previous export")
    monkeypatch.setattr(export, "export_graph", lambda graph, inputs, output, path: path.write_bytes(b"not onnx"))
    with pytest.raises(ExportVerificationError, match="depth_net.onnx: onnxruntime could not run"):
        export_onnx(model_file, out)
    assert [p.name for p in out.iterdir()] == ["depth_net.onnx"]
    assert (out / "depth_net.onnx").read_bytes() == b"previous export"


def test_the_command_refuses_a_missing_model_file_a_file_of_another_kind_and_other_formats(tmp_path, capsys):
    assert cli_main(["model", "export", "--model", str(tmp_path / "absent.pt"), "--out", str(tmp_path / "o")]) == 2
    assert f"{tmp_path / 'absent.pt'}: model file not found" in capsys.readouterr().err
    (tmp_path / "notes.pt").write_text("not a model")
    assert cli_main(["model", "export", "--model", str(tmp_path / "notes.pt"), "--out", str(tmp_path / "o")]) == 2
    assert f"{tmp_path / 'notes.pt'}" in (err := capsys.readouterr().err) and "not a torch file" in err
    with pytest.raises(SystemExit) as caught:
        cli_main(["model", "export", "--model", str(tmp_path / "notes.pt"), "--format", "tflite", "--out", "o"])
    assert caught.value.code == 2 and "invalid choice: 'tflite'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()

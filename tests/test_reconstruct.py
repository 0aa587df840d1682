"""`endoflow reconstruct`: the three input kinds give the same depth for the same frames, every output is
written (atomically, as one folder), bad input fails saying what to provide, and the fusion reconstructs the
renderer's exact surface from ground-truth depth and poses to within about a voxel."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml
from scipy.ndimage import map_coordinates

from endoflow.cli import main as cli
from endoflow.config import ConfigError, Params
from endoflow.data.imageio import read_gray16
from endoflow.data.registry import open_reader
from endoflow.data.frame_encoding import resize_depth, stored_intrinsics
from endoflow.errors import DataFormatError
from endoflow.geometry.pose import rotation_angle_deg
from endoflow.io import file_sha256
from endoflow.models.endoflow_model import build_model
from endoflow.models.model_file import ModelRecord, TrainingBaselines, load_model_file, save_model_file
from endoflow.reconstruction.frames import FrameRange, InputFrame, intrinsics_for, open_frames
from endoflow.reconstruction.fusion import TSDFVolume, read_ply_vertices
from endoflow.reconstruction.measure import run_reconstruction
from endoflow.reconstruction.reconstruct import (
    ADAPTED_MODEL,
    Adaptation,
    CameraPath,
    Chain,
    PathPhotometry,
    RECONSTRUCTION_FORMAT,
    RangeEndShare,
    ReconstructOptions,
    default_voxel_cm,
    frames_per_call,
    predict_frames,
    reconstruct,
)
from endoflow.synth.writers import synthesize_layout
from endoflow.training.adapt import adapt_to_reconstruct_sequence
from tests.module_temp import ModuleTemp
from tests.small_model import small_model_params

SIZE = 64
FRAMES = 8


@pytest.fixture(scope="module")
def params() -> Params:
    return small_model_params(SIZE)


@pytest.fixture(scope="module")
def scene(module_tmp: ModuleTemp, params: Params) -> Path:
    root = module_tmp("scene") / "SimCol3D"
    synthesize_layout("simcol", root, sequences=1, frames=FRAMES, size=SIZE, seed=0, params=params, workers=1,
                      device="cpu")
    return root


@pytest.fixture(scope="module")
def model_file(module_tmp: ModuleTemp, params: Params) -> Path:
    path = module_tmp("model") / "endoflow.pt"
    torch.manual_seed(0)
    model = build_model(params, latent_bank_path=None)


    save_model_file(path, ModelRecord(params=params, state=model.state_dict(), epoch=0, val={}, mlflow_run_id=None,
                                      baselines=default_baselines()))
    return path


def default_baselines() -> TrainingBaselines:
    from tests.test_evaluate import oracle_baselines

    return oracle_baselines()


def sequence(scene: Path, params: Params, name: str = "S1"):
    return next(s for s in open_reader(scene, None, params).sequences() if s.name == name)


def image_folder(scene: Path, params: Params, folder: Path) -> Path:
    folder.mkdir()
    seq = sequence(scene, params)
    for i in range(len(seq)):
        cv2.imwrite(str(folder / f"frame_{i}.png"), seq.load_rgb(i)[..., ::-1])
    return folder


def lossless_video(scene: Path, params: Params, path: Path) -> Path:
    import av

    seq = sequence(scene, params)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("png", rate=30)
        stream.width, stream.height, stream.pix_fmt = SIZE, SIZE, "rgb24"
        for i in range(len(seq)):
            for packet in stream.encode(av.VideoFrame.from_ndarray(seq.load_rgb(i), format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def k_numbers(scene: Path, params: Params) -> str:
    K = sequence(scene, params).K
    return f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"


def run(source_path: Path, model_file: Path, out: Path, params: Params, sequence_name=None, intrinsics=None,
        **options) -> dict:
    frames = open_frames(source_path, sequence_name, params)
    return reconstruct(frames, intrinsics_for(intrinsics, frames), model_file, out,
                       ReconstructOptions(**options))


def recorded_rows(recording: Path) -> dict[str, int]:
    """Rows logged per entity of a Rerun recording (a Transform3D and a Pinhole of one frame are two rows)."""
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(recording).stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


def depth_of(out: Path, index: int) -> np.ndarray:
    unit = json.loads((out / "depth" / "depth.json").read_text())["unit_cm"]
    return read_gray16(out / "depth" / f"{index:06d}.png").astype(np.float64) * unit


# ----------------------------------------------------------------------------------------------- outputs
def test_the_outputs_are_the_same_files_whatever_the_number_of_encoding_and_decoding_threads(
        scene: Path, model_file: Path, params: Params, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import endoflow.reconstruction.reconstruct as reconstruction
    from endoflow.reconstruction import streams

    outputs = {}
    for cores in (2, 16):  # the writer encodes and one thread decodes, then four threads do each
        monkeypatch.setattr(reconstruction, "Encoders", lambda cores=cores: streams.Encoders(cores))
        monkeypatch.setattr(reconstruction, "side_threads", lambda cores=cores: streams.side_threads(cores))
        out = tmp_path / f"cores{cores}"
        run(scene, model_file, out, params, "S1", npy=True)
        # every file but the contact sheet, whose title holds the frames/s
        outputs[cores] = {path.relative_to(out): file_sha256(path) for path in sorted(out.rglob("*"))
                          if path.is_file() and path.suffix in (".png", ".npy", ".mp4", ".ply", ".tum")
                          and path.name != "sheet.png"}
    assert len(outputs[2]) > 3 * FRAMES and outputs[2] == outputs[16]


def test_a_dataset_sequence_gives_depth_path_surface_and_the_scale_that_fits_its_ground_truth(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    out = tmp_path / "out"
    # the untrained model sees everything at about 0.2 cm, where the default voxel (sized for the depth range) is
    # as wide as the view: a voxel of the pixel footprint there gives the view a surface
    summary = run(scene, model_file, out, params, "S1", npy=True, voxel_cm=0.005)
    assert summary["frames"] == FRAMES and summary["size"] == SIZE
    for i in range(FRAMES):
        exact = np.load(out / "depth" / f"{i:06d}.npy")
        assert exact.shape == (SIZE, SIZE) and exact.dtype == np.float32
        np.testing.assert_allclose(depth_of(out, i), exact, atol=summary["depth_unit_cm"] / 2 + 1e-6)
        assert cv2.imread(str(out / "preview" / f"{i:06d}.png")).shape == (SIZE, SIZE, 3)
    tum = [line for line in (out / "trajectory.tum").read_text().splitlines() if not line.startswith("#")]
    assert len(tum) == FRAMES and np.allclose([float(v) for v in tum[0].split()[1:]], [0, 0, 0, 0, 0, 0, 1])
    assert len((out / "trajectory.kitti").read_text().splitlines()) == FRAMES
    assert len(list((out / "simcol" / "pose").glob("FrameBuffer_*_to_FrameBuffer_*.txt"))) == FRAMES - 1
    assert len(read_ply_vertices(out / "points.ply")) == summary["mesh"]["vertices"] > 0
    assert 0 < summary["surface_seconds"] < summary["seconds"]  # the time of the call spent on the surface
    assert summary["ground_truth_scale"]["frames"] == FRAMES and summary["ground_truth_scale"]["median"] > 0
    assert json.loads((out / "reconstruction.json").read_text())["frames"] == FRAMES
    rows = recorded_rows(out / "recording.rrd")
    assert {rows[f"/world/camera/{part}"] for part in ("image", "depth")} == {FRAMES}
    assert rows["/world/camera"] == 2 * FRAMES  # the pose and the intrinsics of each frame
    assert rows["/world/path"] == rows["/world/ground_truth_path"] == rows["/world/surface"] == 1


def test_the_stage_adapts_the_model_to_its_sequence_first_as_the_command_does_and_keeps_it(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    stage = params.replace(
        data=params.data.replace(simcol=params.data.simcol.replace(root=str(scene))),
        reconstruct=params.reconstruct.replace(model=str(model_file), adapt=2, sequences={
            "s1": {"dataset": "simcol", "sequence": "S1", "start": 0, "stop": None, "stride": 1}}))
    adapted = tmp_path / "adapted.pt"
    fit = adapt_to_reconstruct_sequence(stage, "s1", model_file, adapted, tmp_path)
    # the sequence's frames, as `endoflow adapt --sequence` reads them: the same model to the bit
    assert cli(["adapt", str(scene), "--sequence", "S1", "--model", str(model_file), "--out",
                str(tmp_path / "command.pt"), "--steps", "2", "--no-mlflow"]) == 0
    ours, theirs = load_model_file(adapted).state, load_model_file(tmp_path / "command.pt").state
    assert all(torch.equal(ours[key], theirs[key]) for key in ours)
    assert not all(torch.equal(ours[key], value) for key, value in load_model_file(model_file).state.items())

    run_reconstruction(stage, "s1", model_file, tmp_path, Adaptation.of(adapted, fit, kept=True))
    out = tmp_path / "reconstructions" / "s1"
    summary = json.loads((out / "reconstruction.json").read_text())
    assert summary["model"] == ADAPTED_MODEL and (out / ADAPTED_MODEL).read_bytes() == adapted.read_bytes()
    assert summary["adaptation"] == {"steps": 2, "held_out_photometric_before": fit["held_out_photometric_before"],
                                     "held_out_photometric_after": fit["held_out_photometric_after"], "kept": True}
    assert summary["adapted_from"]["parent"]["sha256"] == file_sha256(model_file)
    assert summary["adapted_from"]["steps"] == 2
    # the adapted model's depth
    run(scene, adapted, tmp_path / "direct", params, "S1", fuse=False)
    assert all(np.array_equal(depth_of(out, i), depth_of(tmp_path / "direct", i)) for i in range(FRAMES))


def test_the_stage_reconstructs_with_the_model_as_trained_where_the_fit_is_not_better_and_fits_only_if_asked(
        tmp_path: Path, monkeypatch) -> None:
    from stages import reconstruct as stage

    calls: list = []
    not_better = {"steps": 300, "held_out_photometric_before": 0.05, "held_out_photometric_after": 0.05}
    monkeypatch.setattr(stage, "adapt_to_reconstruct_sequence", lambda *args: calls.append("fit") or not_better)
    monkeypatch.setattr(stage, "run_reconstruction",
                        lambda params, name, model, adaptation: calls.append(adaptation) or {})
    monkeypatch.setattr(stage, "format_measurement", lambda name, result: "")
    for steps in (0, 300):
        (tmp_path / "params.yaml").write_text(yaml.safe_dump({"reconstruct": {"adapt": steps}}))
        monkeypatch.setattr("sys.argv", ["stage", "simcol_S5", "--params", str(tmp_path / "params.yaml")])
        stage.main()
    assert calls[0] is None  # adapt 0: no fit
    assert calls[1] == "fit" and calls[2].kept is False and calls[2].held_out_after == 0.05


def test_an_empty_surface_is_written_and_said_with_the_voxel_that_would_give_one(
        scene: Path, model_file: Path, params: Params, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # the untrained model sees everything at about 0.2 cm, and a voxel of 0.16 cm is as wide as the view
    summary = run(scene, model_file, tmp_path / "out", params, "S1", frames=FrameRange(stop=3), voxel_cm=0.16)
    assert summary["mesh"]["vertices"] == 0 and len(read_ply_vertices(tmp_path / "out" / "points.ply")) == 0
    warning = capsys.readouterr().err
    assert "the fused surface is empty" in warning and "--voxel-cm about the pixel footprint" in warning
    footprint = float(warning.split("footprint there, ")[1].split(" cm")[0])
    finer = run(scene, model_file, tmp_path / "finer", params, "S1", frames=FrameRange(stop=3), voxel_cm=footprint)
    assert finer["mesh"]["vertices"] > 0


def test_a_collapsed_depth_network_is_said_and_its_share_at_the_range_ends_recorded(
        scene: Path, model_file: Path, params: Params, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    working = run(scene, model_file, tmp_path / "working", params, "S1", frames=FrameRange(stop=3), fuse=False)
    assert working["depth_at_range_ends"] == 0.0 and "has collapsed" not in capsys.readouterr().err
    # the finest disparity head saturated: sigmoid(-40) puts every pixel at max_depth, a depth with no gradient
    record = load_model_file(model_file)
    head = "depth_net.decoder.dispconvs.0"
    state = {**record.state, f"{head}.weight": torch.zeros_like(record.state[f"{head}.weight"]),
             f"{head}.bias": torch.full_like(record.state[f"{head}.bias"], -40.0)}
    collapsed_file = tmp_path / "collapsed.pt"
    save_model_file(collapsed_file, replace(record, state=state))
    collapsed = run(scene, collapsed_file, tmp_path / "collapsed", params, "S1", frames=FrameRange(stop=3), fuse=False)
    assert collapsed["depth_at_range_ends"] == 1.0
    assert json.loads((tmp_path / "collapsed" / "reconstruction.json").read_text())["depth_at_range_ends"] == 1.0
    warning = capsys.readouterr().err
    assert "[reconstruct] warning: 100% of the depth of these frames sits at an end of its range" in warning
    assert "has collapsed" in warning
    # --scale multiplies what is written, not what the network put at the end of its range
    halved = run(scene, collapsed_file, tmp_path / "halved", params, "S1", frames=FrameRange(stop=3), fuse=False,
                 scale=0.5)
    assert halved["depth_at_range_ends"] == 1.0 and np.allclose(depth_of(tmp_path / "halved", 0)[32, 32], 10.0,
                                                                rtol=1e-3)


def test_the_share_at_the_range_ends_counts_only_the_pixels_in_view_over_every_frame() -> None:
    cfg = small_model_params(64).model
    valid = np.zeros((4, 4), bool)
    valid[1:3, 1:3] = True  # 4 pixels in view; outside, the depth is 0 (unknown), below min_depth
    at_top, mid = np.where(valid, np.float32(cfg.max_depth), 0), np.where(valid, np.float32(2.0), 0)
    at_top[1, 1] = 2.0  # 3 of the 4 in view at the top
    share = RangeEndShare(cfg)
    share.add(at_top, valid)
    assert share.share == 0.75
    share.add(mid, valid)
    assert share.share == 3 / 8
    assert RangeEndShare(cfg).share == 0.0  # no frame: nothing at the ends


def test_a_frame_that_fusion_refuses_fails_the_call_with_the_option_that_helps_and_leaves_no_output(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    # the untrained model sees everything at about 0.2 cm, some 2.5 million blocks of 8e-8 cm from the origin,
    # beyond the keys' 2^20
    with pytest.raises(ConfigError, match="--voxel-cm"):
        run(scene, model_file, tmp_path / "out", params, "S1", frames=FrameRange(stop=3), voxel_cm=1e-8)
    assert not (tmp_path / "out").exists()


def test_the_default_voxel_is_a_pixels_footprint_at_the_far_part_of_the_known_depth() -> None:
    K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    depth = np.zeros((8, 8), np.float32)
    depth[:5] = np.arange(1, 41, dtype=np.float32).reshape(5, 8)  # 40 known pixels, 1 to 40 cm; the rest unknown
    # the 95th percentile of 1..40 by linear interpolation: 1 + 0.95 * 39 = 38.05 cm, over fx
    assert default_voxel_cm(depth, K) == pytest.approx(38.05 / 50.0, rel=1e-6)  # the quantile in float32
    with pytest.raises(ValueError, match="no known pixel"):
        default_voxel_cm(np.zeros((8, 8), np.float32), K)


def test_depth_at_another_scale_fuses_the_same_surface_at_that_scale(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    # the voxel follows the depth: a model whose depth is 8 times larger (a power of two, so every product is
    # exact) fuses the same surface 8 times larger, voxel for voxel
    one, eight = (run(scene, model_file, tmp_path / f"x{scale}", params, "S1", frames=FrameRange(stop=4), scale=scale)
                  for scale in (1.0, 8.0))
    assert eight["tsdf"]["voxel_cm"] == 8 * one["tsdf"]["voxel_cm"]
    assert one["tsdf"]["voxel_from"] == "the first frame's depth (0.95 quantile)"
    vertices = read_ply_vertices(tmp_path / "x1.0" / "mesh.ply")
    assert len(vertices) > 100
    np.testing.assert_allclose(read_ply_vertices(tmp_path / "x8.0" / "mesh.ply"), 8 * vertices, rtol=1e-6)


def test_a_folder_and_a_lossless_video_of_the_same_frames_give_the_dataset_sequences_depth(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    run(scene, model_file, tmp_path / "dataset", params, "S1", fuse=False)
    folder = image_folder(scene, params, tmp_path / "frames")
    run(folder, model_file, tmp_path / "folder", params, intrinsics=k_numbers(scene, params), fuse=False)
    video = lossless_video(scene, params, tmp_path / "clip.mov")
    summary = run(video, model_file, tmp_path / "video", params, intrinsics=k_numbers(scene, params), fuse=False)
    assert summary["frames"] == FRAMES
    for kind in ("folder", "video"):
        for i in range(FRAMES):
            np.testing.assert_array_equal(depth_of(tmp_path / kind, i), depth_of(tmp_path / "dataset", i))
    stamps = [float(line.split()[0]) for line in (tmp_path / "video" / "trajectory.tum").read_text().splitlines()
              if not line.startswith("#")]
    np.testing.assert_allclose(stamps, np.arange(FRAMES) / 30, atol=1e-6)


def test_start_stop_and_stride_pick_frames_and_name_outputs_by_input_position(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    summary = run(scene, model_file, tmp_path / "out", params, "S1", frames=FrameRange(1, 7, 2), fuse=False)
    assert summary["frames"] == 3 and summary["surface_seconds"] is None  # no surface, no time for it
    assert sorted(p.name for p in (tmp_path / "out" / "depth").glob("*.png")) == \
        ["000001.png", "000003.png", "000005.png"]


def test_a_known_scale_multiplies_depth_and_path_alike(scene: Path, model_file: Path, params: Params,
                                                       tmp_path: Path) -> None:
    run(scene, model_file, tmp_path / "one", params, "S1", fuse=False, npy=True)
    run(scene, model_file, tmp_path / "two", params, "S1", fuse=False, npy=True, scale=2.0)
    np.testing.assert_allclose(np.load(tmp_path / "two" / "depth" / "000003.npy"),
                               2 * np.load(tmp_path / "one" / "depth" / "000003.npy"), rtol=1e-6)
    one, two = (np.loadtxt(tmp_path / name / "trajectory.kitti") for name in ("one", "two"))
    np.testing.assert_allclose(two[:, [3, 7, 11]], 2 * one[:, [3, 7, 11]], rtol=1e-6, atol=1e-9)


def test_bf16_networks_give_nearly_the_float32_depth_and_path_and_the_summary_says_which_ran(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    exact = run(scene, model_file, tmp_path / "float32", params, "S1", fuse=False, npy=True, precision="float32")
    fast = run(scene, model_file, tmp_path / "bf16", params, "S1", fuse=False, npy=True, precision="bf16")
    assert (exact["precision"], fast["precision"]) == ("float32", "bf16")
    depth, rounded = (np.load(tmp_path / name / "depth" / "000003.npy") for name in ("float32", "bf16"))
    known = depth > 0
    relative = np.abs(rounded[known] - depth[known]) / depth[known]
    assert known.mean() > 0.9 and 0 < np.median(relative) < 0.01  # rounded, so not equal: bf16 keeps 8 mantissa bits
    one, other = (np.loadtxt(tmp_path / name / "trajectory.kitti")[:, [3, 7, 11]] for name in ("float32", "bf16"))
    steps, rounded_steps = np.diff(one, axis=0), np.diff(other, axis=0)
    assert np.linalg.norm(rounded_steps - steps) < 0.05 * np.linalg.norm(steps)


def test_the_command_line_takes_the_precision_from_params_yaml_unless_told(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    params_file = tmp_path / "params.yaml"
    params_file.write_text("reconstruct:\n  precision: bf16\n")
    arguments = ["--params", str(params_file), "reconstruct", str(scene), "--sequence", "S1", "--model",
                 str(model_file), "--stop", "2", "--no-fusion", "--out"]
    assert cli([*arguments, str(tmp_path / "from_params")]) == 0
    assert cli([*arguments, str(tmp_path / "told"), "--precision", "float32"]) == 0
    assert json.loads((tmp_path / "from_params" / "reconstruction.json").read_text())["precision"] == "bf16"
    assert json.loads((tmp_path / "told" / "reconstruction.json").read_text())["precision"] == "float32"
    with pytest.raises(SystemExit):
        cli([*arguments, str(tmp_path / "bad"), "--precision", "fp16"])


def test_an_interrupted_run_leaves_the_previous_output_folder_whole(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    folder = image_folder(scene, params, tmp_path / "frames")
    cv2.imwrite(str(folder / "frame_5.png"), np.zeros((SIZE // 2, SIZE, 3), np.uint8))  # damaged mid-way
    out = tmp_path / "out"
    out.mkdir()
    (out / "reconstruction.json").write_text(json.dumps({"format": RECONSTRUCTION_FORMAT, "frames": 3}))
    with pytest.raises(DataFormatError, match=r"frame_5\.png: image of 64x32 px, expected 64x64"):
        run(folder, model_file, out, params, intrinsics=k_numbers(scene, params))
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    assert json.loads((out / "reconstruction.json").read_text())["frames"] == 3
    assert sorted(p.name for p in out.iterdir()) == ["reconstruction.json"]


# --------------------------------------------------------------------------------------------- bad input
def test_frames_without_intrinsics_take_the_learned_camera_else_an_assumed_one_and_say_which(
        scene: Path, params: Params, model_file: Path, tmp_path: Path) -> None:
    from endoflow.config import DATASETS
    from endoflow.data.intrinsics import assumed_intrinsics
    from endoflow.models.endoflow_model import load_trained_model

    folder = image_folder(scene, params, tmp_path / "frames")
    assert intrinsics_for(None, open_frames(folder, None, params)) is None
    assumed = run(folder, model_file, tmp_path / "assumed", params, frames=FrameRange(stop=2), fuse=False)
    assert assumed["intrinsics"].startswith("assumed (a centred pinhole of 140 degrees across the diagonal")
    np.testing.assert_allclose(assumed["K"], assumed_intrinsics((SIZE, SIZE), 140.0))
    # a model that learned its video camera: the focal length twice the assumed one
    model, record = load_trained_model(model_file, torch.device("cpu"))
    with torch.no_grad():
        model.intrinsics.corrections[DATASETS.index("video")] = torch.tensor([np.log(2.0), np.log(2.0), 0.0, 0.0])
    learned_file = tmp_path / "learned.pt"
    save_model_file(learned_file, ModelRecord(record.params, model.state_dict(), 1, {}, None, record.baselines))
    learned = run(folder, learned_file, tmp_path / "learned", params, frames=FrameRange(stop=2), fuse=False)
    assert learned["intrinsics"].startswith("learned by the model for its 'video' camera")
    assert learned["K"][0][0] == pytest.approx(2 * assumed["K"][0][0])
    assert json.loads((tmp_path / "learned" / "reconstruction.json").read_text())["intrinsics"] == learned["intrinsics"]


@pytest.mark.parametrize("content, message", [
    ({"fx": 50, "fy": 50, "cx": 32, "cy": 32, "width": 128, "height": 128},
     "intrinsics for 128x128 px, but the frames are 64x64"),
    ({"fx": 50, "fy": 50, "cx": 32}, "expected fx, fy, cx, cy .* and the width and height"),
    ({"fx": -5, "fy": 50, "cx": 32, "cy": 32, "width": 64, "height": 64}, "do not fit 64x64 px frames"),
])
def test_an_intrinsics_file_that_does_not_fit_the_frames_says_why(
        scene: Path, params: Params, tmp_path: Path, content: dict, message: str) -> None:
    folder = image_folder(scene, params, tmp_path / "frames")
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(content))
    with pytest.raises(DataFormatError, match=message):
        intrinsics_for(str(path), open_frames(folder, None, params))


def test_intrinsics_from_a_json_file_and_a_simcol_cam_txt_are_read(scene: Path, params: Params,
                                                                   tmp_path: Path) -> None:
    frames = open_frames(image_folder(scene, params, tmp_path / "frames"), None, params)
    (tmp_path / "k.json").write_text(json.dumps({"fx": 40, "fy": 41, "cx": 31.5, "cy": 30, "width": 64,
                                                 "height": 64}))
    np.testing.assert_array_equal(intrinsics_for(str(tmp_path / "k.json"), frames),
                                  [[40, 0, 31.5], [0, 41, 30], [0, 0, 1]])
    (tmp_path / "cam.txt").write_text("40 0 31.5\n0 41 30\n0 0 1\n")
    np.testing.assert_array_equal(intrinsics_for(str(tmp_path / "cam.txt"), frames),
                                  [[40, 0, 31.5], [0, 41, 30], [0, 0, 1]])
    with pytest.raises(DataFormatError, match="four numbers fx,fy,cx,cy"):
        intrinsics_for("40,41,31.5", frames)


def test_bad_inputs_fail_saying_what_to_provide(scene: Path, params: Params, tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataFormatError, match="no images found"):
        open_frames(tmp_path / "empty", None, params)
    (tmp_path / "broken.mp4").write_bytes(b"not a video at all" * 100)
    with pytest.raises(DataFormatError, match=r"broken\.mp4: cannot be read as a video"):
        open_frames(tmp_path / "broken.mp4", None, params)
    with pytest.raises(FileNotFoundError, match="no such video, image folder or dataset root"):
        open_frames(tmp_path / "missing.mp4", None, params)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DataFormatError, match="neither a folder of images nor a video"):
        open_frames(tmp_path / "notes.txt", None, params)
    with pytest.raises(DataFormatError, match="no sequence 'S9'; it has 3: B1, O1, S1"):
        open_frames(scene, "S9", params)
    with pytest.raises(DataFormatError, match=r"SimCol3D: is a simcol dataset root: pick a sequence with --sequence "
                                              r"\(it has 3: B1, O1, S1\)"):
        open_frames(scene, None, params)
    with pytest.raises(ValueError, match="multiple of 32"):
        ReconstructOptions(size=50)
    with pytest.raises(ValueError, match="--precision must be one of auto, bf16, float32, got 'fp16'"):
        ReconstructOptions(precision="fp16")
    with pytest.raises(ValueError, match="start < stop"):
        FrameRange(4, 2)


def test_the_command_line_reports_a_model_file_of_another_format(scene: Path, params: Params, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture) -> None:
    torch.save({"format": 99}, tmp_path / "other.pt")
    code = cli(["reconstruct", str(scene), "--sequence", "S1", "--model", str(tmp_path / "other.pt"),
                "--out", str(tmp_path / "out")])
    assert code == 2 and "model file format 99, expected" in capsys.readouterr().err
    assert cli(["reconstruct", str(scene), "--sequence", "S1", "--out", str(tmp_path / "o"), "--size", "50"]) == 2


def test_the_command_line_runs_a_dataset_sequence(scene: Path, model_file: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    assert cli(["reconstruct", str(scene), "--sequence", "S1", "--model", str(model_file), "--out",
                str(tmp_path / "out"), "--stop", "4", "--no-fusion"]) == 0
    assert "4 frames at 64 px" in capsys.readouterr().out
    assert not (tmp_path / "out" / "mesh.ply").exists()


def test_the_command_line_logs_a_reconstruction_into_mlflow_even_without_the_models_run(
        scene: Path, model_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture) -> None:
    from mlflow.tracking import MlflowClient

    monkeypatch.chdir(tmp_path)  # a project folder without params.yaml: the default store, ./mlflow.db
    assert cli(["reconstruct", str(scene), "--sequence", "S1", "--model", str(model_file), "--out", "clip",
                "--stop", "3", "--mlflow"]) == 0
    captured = capsys.readouterr()
    assert "new MLflow run (reconstruct)" in captured.err and "logged to MLflow run" in captured.out
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    run = client.search_runs([client.get_experiment_by_name("endoflow").experiment_id])[0]
    logged = {item.path for item in client.list_artifacts(run.info.run_id, "reconstruct/clip")}
    assert {"reconstruct/clip/sheet.png", "reconstruct/clip/video.mp4", "reconstruct/clip/recording.rrd",
            "reconstruct/clip/mesh.ply", "reconstruct/clip/trajectory.tum"} <= logged


def test_the_pictures_show_frames_depth_path_and_surface(scene: Path, model_file: Path, params: Params,
                                                         tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import av

    from endoflow.reconstruction import pictures, reconstruct as module

    calls = []

    def recording_sheet(*args) -> None:
        calls.append(args)
        pictures.write_contact_sheet(*args)

    monkeypatch.setattr(module, "write_contact_sheet", recording_sheet)
    run(scene, model_file, tmp_path / "out", params, "S1")
    sheet = cv2.imread(str(tmp_path / "out" / "sheet.png"))
    assert sheet is not None and sheet.shape[1] >= 1200
    # the previews' depth range for the colour bar, and the sequence's ground-truth path to draw beside the model's
    (_, _, depth_range, _, _, _, _, gt_positions), = calls
    assert list(depth_range) == json.loads((tmp_path / "out" / "depth" / "depth.json").read_text())["preview_range_cm"]
    assert gt_positions.shape == (FRAMES, 3) and np.isfinite(gt_positions).all()
    with av.open(str(tmp_path / "out" / "video.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == FRAMES


# ----------------------------------------------------------------------------------------------- fusion
def test_ground_truth_depth_along_ground_truth_poses_fuses_to_the_exact_surface_within_a_voxel(
        scene: Path, params: Params) -> None:
    seq = sequence(scene, params)
    K = stored_intrinsics(seq.K, seq.image_size, SIZE)
    frames = [seq.frame(i) for i in range(len(seq))]
    depths = [resize_depth(f.depth_cm, SIZE) for f in frames]
    voxel = default_voxel_cm(depths[0], K)
    volume = TSDFVolume(voxel, 4 * voxel)
    for frame, depth in zip(frames, depths):
        volume.integrate(depth, cv2.resize(frame.rgb, (SIZE, SIZE)), K, frame.T_world_cam)
    mesh = volume.extract_mesh()
    assert len(mesh.vertices) > 1000
    # a vertex lies on the true surface if some frame sees it there (other frames may see a nearer wall in front);
    # GT depth is read between pixel centres (bilinear, inside the valid area): the colon wall is seen at grazing
    # angles, where depth changes by more than a voxel from one pixel to the next
    errors = np.full(len(mesh.vertices), np.inf)
    for frame, depth in zip(frames, depths):
        cam = (mesh.vertices - frame.T_world_cam[:3, 3]) @ frame.T_world_cam[:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]
            v = K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
        seen = (cam[:, 2] > 0) & (u >= 0) & (u <= SIZE - 1) & (v >= 0) & (v <= SIZE - 1)
        gt = np.zeros(len(cam))
        gt[seen] = map_coordinates(depth.astype(np.float64), [v[seen], u[seen]], order=1)
        seen &= gt > 0
        errors[seen] = np.minimum(errors[seen], np.abs(cam[seen, 2] - gt[seen]))
    assert np.isfinite(errors).mean() > 0.95  # the surface lies where the frames looked
    median = np.median(errors[np.isfinite(errors)])
    assert median < voxel, (median, voxel)


def test_a_long_path_stays_rigid_however_many_float32_steps_it_chains() -> None:

    rng = np.random.default_rng(0)
    angle = 0.01
    step = np.eye(4)
    step[:3, :3] = cv2.Rodrigues(np.array([angle, 2 * angle, -angle]))[0]
    step[:3, 3] = (0.01, 0.0, 0.1)
    path, chain = CameraPath(), Chain()
    depth = np.ones((4, 4), np.float32)
    for i in range(3000):
        noisy = (step + rng.normal(0, 1e-7, (4, 4)) * [[1, 1, 1, 0]] * 4).astype(np.float32)  # float32 network output
        network = chain.step(None if i == 0 else noisy, 1.0)
        path.add(InputFrame(i, i / 30, np.zeros((4, 4, 3), np.uint8)), network, network, depth, 4)
    rotations = np.stack(path.poses)[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-12)


def test_a_refined_path_is_written_with_the_networks_own_beside_it(scene: Path, model_file: Path, params: Params,
                                                                   tmp_path: Path) -> None:
    from endoflow.data.trajectory_files import read_tum
    from endoflow.geometry.direct_alignment import tracker_settings
    from endoflow.reconstruction.reconstruct import NETWORK_PATH_FILE

    refined = run(scene, model_file, tmp_path / "refined", params, "S1", refine=tracker_settings(params.refine))
    plain = run(scene, model_file, tmp_path / "plain", params, "S1")
    assert refined["path"]["refined"] and refined["path"]["keyframes"] >= 1
    assert refined["path"]["rotation_smoothing_frames"] == params.refine.rotation_smoothing > 0
    assert (refined["path"]["scale_from"], plain["path"]["scale_from"]) == ("depth", "pose network")
    assert not plain["path"]["refined"] and not (tmp_path / "plain" / NETWORK_PATH_FILE).exists()
    # the ground-truth-free figure: the plain path is the network's own
    errors = plain["path"]["photometric_error"]
    assert set(errors) == {"path", "network", "constant_velocity"} and errors["path"] == errors["network"]
    assert refined["path"]["photometric_error"]["path"] < refined["path"]["photometric_error"]["network"]
    # the network's own chain is the unrefined reconstruction's path, to the bit
    _, network = read_tum(tmp_path / "refined" / NETWORK_PATH_FILE)
    np.testing.assert_array_equal(network, read_tum(tmp_path / "plain" / "trajectory.tum")[1])
    _, path = read_tum(tmp_path / "refined" / "trajectory.tum")
    # both start at the origin; the refined path's first orientation is smoothed like every other
    assert len(path) == len(network) and np.array_equal(path[0, :3, 3], network[0, :3, 3])
    assert rotation_angle_deg(path[0, :3, :3]) < 0.5 and np.array_equal(network[0], np.eye(4))


def test_the_refined_path_written_is_the_aligned_one_with_its_orientations_smoothed(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    """The tracker goes on from the poses as aligned, so smoothing changes only what is written and fused: the path
    of a run with smoothing is the path of a run without it, smoothed afterwards. A window of 1 frame reaches 3:
    of the 8 frames, frames 0-4 are written while the tracker goes on, the rest at the end."""
    from endoflow.data.trajectory_files import read_tum
    from endoflow.geometry.direct_alignment import tracker_settings
    from endoflow.geometry.path_smoothing import smooth_path_orientations

    settings = tracker_settings(params.refine)
    smoothed = run(scene, model_file, tmp_path / "smoothed", params, "S1",
                   refine=replace(settings, rotation_smoothing=1.0))
    aligned = run(scene, model_file, tmp_path / "aligned", params, "S1", refine=replace(settings, rotation_smoothing=0))
    assert smoothed["frames"] == aligned["frames"] == FRAMES
    assert (smoothed["path"]["rotation_smoothing_frames"], aligned["path"]["rotation_smoothing_frames"]) == (1.0, 0)
    _, path = read_tum(tmp_path / "smoothed" / "trajectory.tum")
    _, as_aligned = read_tum(tmp_path / "aligned" / "trajectory.tum")
    assert not np.allclose(path[:, :3, :3], as_aligned[:, :3, :3], atol=1e-6)
    np.testing.assert_allclose(path, smooth_path_orientations(as_aligned, 1.0), atol=1e-6)
    np.testing.assert_array_equal(path[:, :3, 3], as_aligned[:, :3, 3])  # the positions are the tracker's


def test_with_the_depth_rescaled_to_its_keyframes_the_depth_written_is_the_networks_times_the_trackers_factor(
        scene: Path, model_file: Path, params: Params, tmp_path: Path) -> None:
    """``refine.depth_scale``: the first frame keeps its depth, the others are written (and fused) times the factor
    the tracker fitted, and the summary says the factors' range; without it nothing is rescaled."""
    from endoflow.geometry.direct_alignment import tracker_settings

    settings = tracker_settings(params.refine)
    rescaled = run(scene, model_file, tmp_path / "rescaled", params, "S1", refine=replace(settings, depth_scale=True))
    plain = run(scene, model_file, tmp_path / "plain", params, "S1", refine=settings)
    assert plain["path"]["depth_rescaled"] is None
    factors = rescaled["path"]["depth_rescaled"]
    assert factors["min"] <= 1.0 <= factors["max"] and factors["min"] != factors["max"]  # the first frame's is 1
    unit = json.loads((tmp_path / "plain" / "depth" / "depth.json").read_text())["unit_cm"]
    np.testing.assert_array_equal(depth_of(tmp_path / "rescaled", 0), depth_of(tmp_path / "plain", 0))
    last = FRAMES - 1
    np.testing.assert_allclose(depth_of(tmp_path / "rescaled", last),
                               depth_of(tmp_path / "plain", last) * factors["last"], atol=unit * (1 + factors["last"]))


def test_the_black_border_of_a_circular_field_of_view_gets_no_depth(scene: Path, model_file: Path, params: Params,
                                                                    tmp_path: Path) -> None:
    folder = image_folder(scene, params, tmp_path / "frames")
    v, u = np.mgrid[:SIZE, :SIZE]
    inside = ((u - (SIZE - 1) / 2) ** 2 + (v - (SIZE - 1) / 2) ** 2 <= (0.45 * SIZE) ** 2)
    for path in folder.iterdir():
        cv2.imwrite(str(path), cv2.imread(str(path)) * inside[..., None].astype(np.uint8))
    summary = run(folder, model_file, tmp_path / "out", params, intrinsics=k_numbers(scene, params))
    # pi 0.45^2 = 0.64 of the frame, less the 2-px rim: pi (0.45 - 2 / 64)^2 = 0.55
    assert 0.53 < summary["field_of_view"]["share"] < 0.57
    depth = depth_of(tmp_path / "out", 0)
    assert (depth[~inside] == 0).all() and (depth[24:40, 24:40] > 0).all()


def test_frames_predicted_in_batches_are_the_frames_predicted_one_by_one() -> None:
    torch.manual_seed(0)
    model = build_model(small_model_params(SIZE), None).eval()
    images = torch.rand(7, 3, SIZE, SIZE)
    with torch.no_grad():
        one_by_one = [predict_frames(model, images[i:i + 1], images[i - 1:i] if i else None, 2.0, Path("m.pt"), [i])[0]
                      for i in range(7)]
        batched = (predict_frames(model, images[:4], None, 2.0, Path("m.pt"), [0, 1, 2, 3])
                   + predict_frames(model, images[4:], images[3:4], 2.0, Path("m.pt"), [4, 5, 6]))
    assert batched[0][1] is None and one_by_one[0][1] is None  # the video's first frame has no step
    for (depth, step), (alone, alone_step) in zip(batched, one_by_one):
        assert np.allclose(depth, alone, rtol=1e-4)
        assert step is None or np.allclose(step, alone_step, atol=1e-5)


def test_small_frames_share_a_network_call_on_a_cpu_and_large_ones_go_alone() -> None:
    cpu, gpu = torch.device("cpu"), torch.device("cuda")
    assert frames_per_call(64, cpu) == 8 and frames_per_call(128, cpu) == 2 and frames_per_call(480, cpu) == 1
    assert frames_per_call(480, gpu) == frames_per_call(64, gpu) > 1


@pytest.mark.parametrize("refined", [True, False], ids=["refined", "network's"])
def test_each_paths_photometric_error_is_the_mean_over_frames_of_its_own_steps_warp_error(
        refined: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    import endoflow.reconstruction.reconstruct as reconstruction
    from endoflow.losses.photometric import view_synthesis_error

    monkeypatch.setattr(reconstruction, "PHOTOMETRY_READ_FRAMES", 2)  # read back after two frames, then at the end
    rng = np.random.default_rng(5)
    K = np.array([[24.0, 0.0, 15.5], [0.0, 24.0, 15.5], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:32, 0:32]
    frames = [np.clip(np.stack([4 * u + 3 * i, 4 * v, 128 + 2 * u - v], -1) + rng.normal(0, 6, (32, 32, 3)), 0, 255)
              .astype(np.uint8) for i in range(4)]
    depths = [np.full((32, 32), 4.0 + i, np.float32) for i in range(4)]
    for depth in depths:
        depth[:, :3] = 0  # unknown: outside the field of view
    network = [np.eye(4)]
    for i in range(1, 4):
        network.append(network[-1] @ pose_step(-0.01, (0.0, 0.02, 0.1)))
    written = [np.eye(4)]  # the path written: refined, or the network's own
    for i in range(1, 4):
        written.append(written[-1] @ pose_step(0.02 * i, (0.01, 0.0, 0.05 * i)) if refined else network[i])
    mean_step = pose_step(0.005, (0.0, 0.0, 0.08))
    path, photometry = CameraPath(), PathPhotometry(K, mean_step, 1, 1.0)
    for i in range(4):
        path.add(InputFrame(i, i / 30, frames[i]), written[i], network[i], depths[i], 32)
        photometry.add(frames[i], depths[i], path)

    def alone(i: int, T_cur_prev: np.ndarray) -> float:
        image = [torch.from_numpy(frames[j]).permute(2, 0, 1).float()[None] / 255 for j in (i - 1, i)]
        depth = torch.from_numpy(depths[i - 1])[None, None]
        return float(view_synthesis_error(image[0], image[1], depth, torch.from_numpy(T_cur_prev).float()[None],
                                          torch.from_numpy(K).float()[None], depth > 0)[0])

    expected = {name: np.mean([alone(i, np.linalg.inv(poses[i]) @ poses[i - 1] if poses is not None
                                     else np.linalg.inv(mean_step)) for i in range(1, 4)])
                for name, poses in (("path", written), ("network", network), ("constant_velocity", None))}
    means = photometry.means()
    assert means == pytest.approx(expected, rel=1e-6)
    # three different steps (a mix-up of names would show), or the network's written as the path
    assert len(set(means.values())) == (3 if refined else 2)


def pose_step(angle: float, translation: tuple[float, float, float]) -> np.ndarray:
    step = np.eye(4)
    step[:3, :3] = cv2.Rodrigues(np.array([0.0, angle, 0.0]))[0]
    step[:3, 3] = translation
    return step


def test_a_datasets_and_a_folders_frames_decode_in_any_order_as_they_stream(scene: Path, params: Params,
                                                                             tmp_path: Path) -> None:
    dataset = open_frames(scene, "S1", params)
    folder = tmp_path / "frames"
    folder.mkdir()
    for frame in dataset.frames(FrameRange()):
        cv2.imwrite(str(folder / f"{frame.index}.png"), np.ascontiguousarray(frame.rgb[..., ::-1]))
    selection = FrameRange(1, None, 2)
    for source in (dataset, open_frames(folder, None, params)):
        streamed = list(source.frames(selection))
        backwards = [read() for read in reversed(list(source.readers(selection)))][::-1]
        assert [frame.index for frame in backwards] == [frame.index for frame in streamed] == \
            list(range(1, FRAMES, 2))
        for alone, together in zip(backwards, streamed):
            for name in ("rgb", "depth_cm", "T_world_cam"):
                assert np.array_equal(getattr(alone, name), getattr(together, name)), name

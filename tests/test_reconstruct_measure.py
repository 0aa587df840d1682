"""Measuring a reconstruction against exact ground truth: a reconstruction that *is* the ground truth, seen from
another world frame at another scale, measures as perfect (its Sim(3) is recovered, its surface lies on the
renderer's); the floor is within a voxel; the trivial baselines are worse; the distances mean what they say;
input that cannot be measured says why."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from endoflow.config import Params
from endoflow.data.frame_encoding import depth_to_counts, encode_png, resize_depth, resize_rgb, stored_intrinsics
from endoflow.data.trajectory_files import write_tum
from endoflow.geometry.pose import invert_pose
from endoflow.io import write_bytes, write_json
from endoflow.models.model_file import TrainingBaselines
from endoflow.reconstruction import measure
from endoflow.reconstruction.frames import DatasetFrames, FrameRange, FolderFrames
from endoflow.reconstruction.fusion import TSDFVolume, write_ply
from endoflow.reconstruction.measure import (
    DISTANCE_CAP_CM,
    PATH_ROWS,
    back_project,
    format_measurement,
    headline_measurement,
    measure_reconstruction,
    metrics_summary,
    path_errors,
    surface_errors,
    SurfacePoints,
)
from endoflow.synth.writers import synthesize_layout
from tests.module_temp import ModuleTemp
from tests.samples import C3VD_SAMPLE
from tests.small_model import small_model_params

SIZE = 64
FRAMES = 24  # 3 cm of a real-speed path: few frames see the surface from too few places to carve the fusion
UNIT_CM = 0.001


@pytest.fixture(scope="module")
def params() -> Params:
    return small_model_params(SIZE)


@pytest.fixture(scope="module")
def source(module_tmp: ModuleTemp, params: Params) -> DatasetFrames:
    root = module_tmp("scene") / "SimCol3D"
    synthesize_layout("simcol", root, sequences=1, frames=FRAMES, size=SIZE, seed=1, params=params, workers=1,
                      device="cpu")
    return DatasetFrames(root, "S1", params)


def similarity(seed: int = 3) -> tuple[np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q)), rng.uniform(-20, 20, 3), 0.37


def baselines() -> TrainingBaselines:
    step = np.eye(4)
    step[2, 3] = 0.4
    return TrainingBaselines(mean_depth_cm=6.0, mean_depth_map=np.full((SIZE, SIZE), 6.0, np.float32),
                             mean_relative_pose=step)


def write_ground_truth_as_reconstruction(source: DatasetFrames, out: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """A reconstruction folder whose depth and path are the ground truth's, expressed in a world frame and at a
    scale of its own (``p_own = s^-1 R^T (p_gt - t)``), as a monocular method would give them."""
    R, t, s = similarity()
    K = stored_intrinsics(source.K, source.native_size, SIZE)
    voxel = 0.15
    volume = TSDFVolume(voxel / s, 4 * voxel / s)
    poses, stamps = [], []
    for frame in source.frames(FrameRange()):
        gt = frame.T_world_cam
        own = np.eye(4)
        own[:3, :3] = R.T @ gt[:3, :3]
        own[:3, 3] = R.T @ (gt[:3, 3] - t) / s
        depth = resize_depth(frame.depth_cm.astype(np.float32), SIZE) / s
        counts, _ = depth_to_counts(depth, UNIT_CM)
        write_bytes(out / "depth" / f"{frame.index:06d}.png", encode_png(counts))
        volume.integrate(depth, resize_rgb(frame.rgb, SIZE), K, own)
        poses.append(own)
        stamps.append(frame.timestamp)
    write_tum(out / "trajectory.tum", np.array(stamps), np.stack(poses))
    mesh = volume.extract_mesh()
    write_ply(out / "mesh.ply", mesh.vertices, mesh.colours, mesh.triangles)
    write_json(out / "reconstruction.json", {
        "frame_range": {"start": 0, "stop": None, "stride": 1}, "size": SIZE, "K": K.tolist(),
        "depth_unit_cm": UNIT_CM, "frames_per_second": 10.0,
        "tsdf": {"voxel_cm": volume.voxel_cm, "trunc_cm": volume.trunc_cm},  # in its own unit, as it fused
        "ground_truth_scale": {"median": s, "spread": 0.0, "frames": len(poses)}})
    return R, t, s


@pytest.fixture(scope="module")
def measured(source: DatasetFrames, module_tmp: ModuleTemp) -> tuple[dict, tuple]:
    out = module_tmp("reconstruction")
    truth = write_ground_truth_as_reconstruction(source, out)
    return measure_reconstruction(source, out, baselines()), truth


# ------------------------------------------------------------------------------------------ the protocol
def test_ground_truth_in_another_frame_and_scale_measures_as_perfect(measured) -> None:
    result, (_, _, s) = measured
    model = result["path"]["model"]
    assert model["scale"] == pytest.approx(s, rel=1e-6)
    assert model["scale_over_depth"] == pytest.approx(1.0, rel=1e-6)  # depth and path at one scale
    assert model["ate_rmse"] < 1e-5 and model["rpe_trans"] < 1e-5 and model["rpe_rot"] < 1e-3
    assert result["frames"] == FRAMES and result["depth_scale"] == pytest.approx(s)
    floor, surface = result["surface"]["ground_truth"], result["surface"]["model"]
    voxel = result["voxel_cm"]
    # the same fusion of the same geometry in other units, on a grid turned with the frame: as complete as the
    # floor, and as accurate up to the grid's own artifacts (the false surface at the back of the truncation band
    # moves with the grid: docs/reconstruction.md)
    assert surface["completeness_median"] == pytest.approx(floor["completeness_median"], abs=0.25 * voxel)
    assert surface["accuracy_median"] == pytest.approx(floor["accuracy_median"], abs=voxel)
    assert surface["completeness_ratio"] > 0.95


@pytest.mark.skipif(not C3VD_SAMPLE.is_dir(), reason=f"real C3VD sample not found at {C3VD_SAMPLE}")
def test_the_real_c3vd_sample_as_its_own_reconstruction_measures_as_perfect(params: Params, tmp_path: Path) -> None:
    """Real registered poses (pose.txt, rotations rounded to six digits) through the same protocol: the path of the
    ground truth, in another frame and scale, is recovered."""
    source = DatasetFrames(C3VD_SAMPLE, "cecum_t1_a", params)
    _, _, s = write_ground_truth_as_reconstruction(source, tmp_path)
    result = measure_reconstruction(source, tmp_path, baselines())
    model = result["path"]["model"]
    assert result["frames"] == 10 and model["scale"] == pytest.approx(s, rel=1e-6)
    assert model["ate_rmse"] < 1e-5 and model["rpe_trans"] < 1e-5 and model["rpe_rot"] < 1e-3
    assert result["surface"]["model"]["completeness_ratio"] > 0.9


def test_the_floor_is_within_a_voxel_and_the_trivial_baselines_are_worse(measured) -> None:
    result, _ = measured
    voxel = result["voxel_cm"]
    floor = result["surface"]["ground_truth"]
    assert floor["accuracy_median"] < voxel and floor["completeness_median"] < voxel
    assert floor["completeness_ratio"] > 0.95
    for row in ("constant_depth", "constant_velocity", "trivial"):
        assert result["surface"][row]["accuracy_median"] > 2 * floor["accuracy_median"], row
    assert result["path"]["constant_velocity"]["ate_rmse"] > 10 * result["path"]["model"]["ate_rmse"]
    assert result["path"]["constant_velocity"]["scale"] == 1.0  # metric: aligned without scale


def test_every_path_row_is_measured_and_the_summary_is_plain_json(measured, tmp_path: Path) -> None:
    result, _ = measured
    assert set(result["path"]) == set(PATH_ROWS)
    # without a refined path the network's own is the path itself
    assert result["path"]["network"]["ate_rmse"] == result["path"]["model"]["ate_rmse"]
    write_json(tmp_path / "measurement.json", metrics_summary(result))


def test_the_measurement_reads_as_two_tables(measured) -> None:
    result = measured[0]
    text = format_measurement("S1", result)
    assert text.count("\n| model |") == 2 and "| ground_truth |" in text and "| trivial |" in text
    assert (f"fused at the ground truth's scale, voxel {result['voxel_cm']:.3g} cm ({result['depth_scale']:.3g} x "
            f"the reconstruction's)") in text.splitlines()[0]


# -------------------------------------------------------------------------------------------- the parts
def test_path_alignment_recovers_a_known_similarity_and_measures_what_remains() -> None:
    rng = np.random.default_rng(0)
    gt = np.tile(np.eye(4), (30, 1, 1))
    gt[:, :3, 3] = np.cumsum(rng.normal(0, 1, (30, 3)), axis=0)
    R, t, s = similarity()
    own = gt.copy()
    own[:, :3, :3] = R.T @ gt[:, :3, :3]
    own[:, :3, 3] = (gt[:, :3, 3] - t) @ R / s
    result = path_errors(gt, own, with_scale=True)
    alignment = result["alignment"]
    np.testing.assert_allclose(alignment.rotation, R, atol=1e-9)
    np.testing.assert_allclose(alignment.translation, t, atol=1e-8)
    assert alignment.scale == pytest.approx(s) and result["ate_rmse"] < 1e-8
    noisy = own.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.1, (30, 3)) / s  # 1 mm per axis in the ground truth's units
    assert path_errors(gt, noisy, with_scale=True)["ate_rmse"] == pytest.approx(0.1 * np.sqrt(3), rel=0.3)


def test_accuracy_and_completeness_are_distances_each_way() -> None:
    grid = np.stack(np.meshgrid(np.arange(0, 10.0, 0.1), np.arange(0, 10.0, 0.1)), -1).reshape(-1, 2)
    plane = np.column_stack([grid, np.zeros(len(grid))])
    half_lifted = plane[plane[:, 0] < 5] + [0, 0, 0.3]  # half of the plane, 3 mm above it
    figures = surface_errors(half_lifted, plane, voxel_cm=0.1)
    assert figures["accuracy_mean"] == pytest.approx(0.3) and figures["accuracy_median"] == pytest.approx(0.3)
    assert figures["completeness_median"] > 0.3  # the missing half is far from the mesh
    assert figures["completeness_ratio"] == 0.0  # nothing within 2 voxels (0.2 cm)
    assert surface_errors(np.zeros((0, 3)), plane, 0.1)["completeness_ratio"] == 0.0


def test_ground_truth_points_follow_the_surface_seen_not_the_frame_count() -> None:
    K = np.array([[32.0, 0, 31.5], [0, 32.0, 31.5], [0, 0, 1]])
    depth = np.full((64, 64), 5.0, np.float32)
    points = SurfacePoints(0.05)
    points.add(depth, K, np.eye(4))
    once = len(points.points())
    for _ in range(5):
        points.add(depth, K, np.eye(4))
    assert len(points.points()) == once
    np.testing.assert_allclose(back_project(depth, K, np.eye(4))[:, 2], 5.0)


# -------------------------------------------------------------------------------------------- bad input
def test_a_reconstruction_without_a_surface_cannot_be_measured(source: DatasetFrames, tmp_path: Path) -> None:
    write_ground_truth_as_reconstruction(source, tmp_path)
    summary = json.loads((tmp_path / "reconstruction.json").read_text())
    write_json(tmp_path / "reconstruction.json", {**summary, "tsdf": None})
    with pytest.raises(ValueError, match="run without fusion; measuring needs its surface"):
        measure_reconstruction(source, tmp_path, baselines())


def test_an_empty_mesh_has_no_accuracy_and_every_ground_truth_point_missed(tmp_path: Path) -> None:
    # no NaN: the figures go to JSON, which has none (writing one is refused)
    gt = np.random.default_rng(0).uniform(0, 1, (50, 3))
    errors = surface_errors(np.zeros((0, 3)), gt, voxel_cm=0.1)
    assert errors["accuracy_mean"] is None and errors["accuracy_median"] is None
    assert errors["completeness_median"] == DISTANCE_CAP_CM and errors["completeness_ratio"] == 0.0
    write_json(tmp_path / "m.json", errors)
    table = format_measurement("empty", {"frames": 1, "voxel_cm": 0.1, "depth_scale": 1.0, "frames_per_second": 1.0, "path": {},
                                         "surface": {"model": errors}})
    assert "none (empty mesh) / none (empty mesh)" in table


def test_the_headline_of_an_empty_mesh_logs_to_mlflow_without_its_missing_accuracy(
        measured, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    result, _ = measured
    empty = {**result, "surface": {**result["surface"], "model": surface_errors(
        np.zeros((0, 3)), np.ones((5, 3)), voxel_cm=0.1)}}
    logged: dict = {}

    class Run:  # the model's MLflow run, as log_reconstruction returns it
        def log_metrics(self, metrics: dict) -> None:
            logged.update(metrics)

        def show_in_runs_table(self, metrics: dict) -> None:
            pass

        def log_table(self, rows: list, name: str) -> None:
            logged["table"] = rows

    monkeypatch.setattr(measure, "log_reconstruction", lambda *args: Run())
    measure.log_measurement(None, tmp_path, "run", "S1", tmp_path, empty)
    assert headline_measurement(empty)["accuracy_cm"] is None
    assert set(logged) == {"reconstruct/S1/ate_cm", "reconstruct/S1/completeness_2vox_pct", "table"}


def test_input_without_ground_truth_says_which_frame_lacks_it(source: DatasetFrames, tmp_path: Path) -> None:
    import cv2

    write_ground_truth_as_reconstruction(source, tmp_path / "out")
    (tmp_path / "frames").mkdir()
    for frame in source.frames(FrameRange()):
        cv2.imwrite(str(tmp_path / "frames" / f"{frame.index}.png"), frame.rgb[..., ::-1])
    with pytest.raises(ValueError, match="frame 0 has no ground-truth depth and pose"):
        measure_reconstruction(FolderFrames(tmp_path / "frames"), tmp_path / "out", baselines())


def test_a_trajectory_of_another_length_is_named(source: DatasetFrames, tmp_path: Path) -> None:
    write_ground_truth_as_reconstruction(source, tmp_path)
    lines = (tmp_path / "trajectory.tum").read_text().splitlines()
    (tmp_path / "trajectory.tum").write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(ValueError, match=f"trajectory.tum has {FRAMES - 1} poses for {FRAMES} frames"):
        measure_reconstruction(source, tmp_path, baselines())

"""The C3VD reader: the real sample's bytes (frames, depth TIFFs, the pose file, the fisheye calibration), the
undistortion to a pinhole, and every bad input named."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from endoflow.config import Params
from endoflow.data.c3vd import OmnidirectionalCamera, decode_depth, read_calibration, read_poses, undistortion_maps
from endoflow.data.check import check_dataset
from endoflow.data.registry import detect_dataset, open_reader
from endoflow.errors import DataFormatError
from tests.samples import C3VD_SAMPLE

needs_sample = pytest.mark.skipif(not C3VD_SAMPLE.is_dir(), reason=f"real C3VD sample not found at {C3VD_SAMPLE}")
SEQUENCE = C3VD_SAMPLE / "cecum_t1_a"


def small_camera() -> OmnidirectionalCamera:
    return OmnidirectionalCamera(width=40, height=30, cx=19.7, cy=14.2, a0=25.0, a2=-0.004, a3=2e-5, a4=-1e-7,
                                 e=0.999, f=0.002, g=-0.003)


@needs_sample
def test_the_real_sample_reads_as_one_sequence_with_its_frames_depth_poses_and_pinhole():
    assert detect_dataset(C3VD_SAMPLE) == "c3vd"
    (sequence,) = open_reader(C3VD_SAMPLE, None, Params()).sequences()
    assert (sequence.name, sequence.group, sequence.split) == ("cecum_t1_a", "cecum", "train")
    assert sequence.frame_ids == list(range(0, 271, 30)) and sequence.image_size == (1080, 1350)
    camera = read_calibration(C3VD_SAMPLE / "calibration" / "cfhq190l_omnidirectional_values.txt")
    np.testing.assert_allclose(sequence.K, [[camera.a0, 0, camera.cx], [0, camera.a0, camera.cy], [0, 0, 1]])
    # pose.txt line 1, column-major, mm -> cm
    np.testing.assert_allclose(sequence.pose(0)[:3, 3], [5.52977, 3.93949, -10.9741])
    # pose.txt's six significant digits leave its rotations orthonormal to about 1.5e-6: the reader makes them
    # exact, which trajectory tools check to 1e-6 (evo refused the sample's path before)
    rotations = sequence.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-12)
    assert np.linalg.det(rotations) == pytest.approx(np.ones(len(rotations)), abs=1e-12)
    as_written = np.loadtxt(SEQUENCE / "pose.txt", delimiter=",")[sequence.frame_ids].reshape(-1, 4, 4)
    np.testing.assert_allclose(rotations, as_written.transpose(0, 2, 1)[:, :3, :3], atol=2e-6)
    frame = sequence.frame(0)
    assert frame.rgb.shape == (1080, 1350, 3) and frame.depth_cm.dtype == np.float32


@needs_sample
def test_the_sample_files_decode_as_its_readme_measured():
    raw = decode_depth(SEQUENCE / "0000_depth.tiff")
    assert np.median(raw[raw > 0]) == pytest.approx(3.25, abs=0.01)  # 32.5 mm
    poses = read_poses(SEQUENCE / "pose.txt", list(range(276)), [])
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.sum() == pytest.approx(5.47, abs=0.01)  # the 54.7 mm path


@needs_sample
def test_the_ground_truth_explains_the_motion_after_undistortion():
    report = check_dataset(C3VD_SAMPLE, "c3vd", Params())
    assert report["ok"] and report["sequences"][0]["ratio"] < 0.6


def test_the_pinhole_sees_what_the_fisheye_sees_along_each_ray():
    camera = small_camera()
    # a ray through the fisheye at (x, y) on the sensor: (x, y, polynomial(rho)); project() inverts that
    rng = np.random.default_rng(0)
    sensor = rng.uniform(-12, 12, (50, 2))
    rays = np.concatenate([sensor, camera.polynomial(np.linalg.norm(sensor, axis=1))[:, None]], axis=1)
    expected = np.stack([camera.e * sensor[:, 0] + camera.f * sensor[:, 1] + camera.cx,
                         camera.g * sensor[:, 0] + sensor[:, 1] + camera.cy], axis=1)
    np.testing.assert_allclose(camera.project(rays * 3.7), expected, atol=1e-3)  # any point along the ray
    map_u, map_v = undistortion_maps(camera, None)
    # the pinhole's principal point looks down the axis, as the fisheye's centre does
    centre_u, centre_v = np.interp(camera.cx, np.arange(40), map_u[14]), np.interp(camera.cy, np.arange(30),
                                                                                   map_v[:, 20])
    assert (centre_u, centre_v) == pytest.approx((camera.cx, camera.cy), abs=0.05)


def write_sequence(root: Path, frames: int = 3) -> Path:
    """A tiny C3VD layout: the small camera's calibration (its centre counted from pixel 1, as MATLAB writes it),
    colour PNGs, depth TIFFs, a column-major pose file."""
    (root / "calibration").mkdir(parents=True)
    camera = small_camera()
    (root / "calibration" / "cfhq190l_omnidirectional_values.txt").write_text(
        " ".join(str(v) for v in (camera.width, camera.height, camera.cx + 1, camera.cy + 1, camera.a0, camera.a2, camera.a3,
                                  camera.a4, camera.e, camera.f, camera.g)))
    folder = root / "sigmoid_t1_a"
    folder.mkdir()
    lines = []
    for i in range(frames):
        cv2.imwrite(str(folder / f"{i}_color.png"), np.full((30, 40, 3), 100 + 10 * i, np.uint8))
        cv2.imwrite(str(folder / f"{i:04d}_depth.tiff"), np.full((30, 40), 20000, np.uint16))
        pose = np.eye(4)
        pose[2, 3] = 1.5 * i  # mm
        lines.append(",".join(str(v) for v in pose.T.ravel()))
    (folder / "pose.txt").write_text("\n".join(lines) + "\n")
    return folder


def test_a_tiny_layout_reads_in_cm_with_depth_0_where_the_fisheye_sees_nothing(tmp_path: Path):
    write_sequence(tmp_path)
    (sequence,) = open_reader(tmp_path, "c3vd", Params()).sequences()
    np.testing.assert_allclose(sequence.poses[:, 2, 3], [0.0, 0.15, 0.3])
    depth = sequence.frame(1).depth_cm
    assert depth[15, 20] == pytest.approx(20000 / 65535 * 10, rel=1e-6)


def pose_file_lines(poses: list[np.ndarray]) -> str:
    """pose.txt's layout: each 4x4 column by column, its numbers with six significant digits as C3VD writes them."""
    return "".join(",".join(f"{v:g}" for v in pose.T.ravel()) + "\n" for pose in poses)


def test_rotations_rounded_in_the_file_are_read_as_exact_rotations(tmp_path: Path):
    folder = write_sequence(tmp_path)
    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(axis * np.radians(67.0))[0]  # its rounding leaves R^T R 1.5e-6 off
    (folder / "pose.txt").write_text(pose_file_lines([pose] * 3))
    as_written = np.loadtxt(folder / "pose.txt", delimiter=",")[0].reshape(4, 4).T[:3, :3]
    assert np.abs(as_written.T @ as_written - np.eye(3)).max() > 1e-6  # beyond what evo accepts as a rotation
    rotations = read_poses(folder / "pose.txt", [0, 1, 2], [])[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (3, 3, 3)),
                               atol=1e-14)
    np.testing.assert_allclose(rotations, np.broadcast_to(as_written, (3, 3, 3)), atol=2e-6)


def test_a_frame_without_a_pose_is_reported_and_the_others_made_exact_without_warnings(tmp_path: Path):
    folder = write_sequence(tmp_path)
    lines = pose_file_lines([np.eye(4)] * 3).splitlines()
    lines[1] = ",".join(["nan"] * 15 + ["1"])
    (folder / "pose.txt").write_text("\n".join(lines) + "\n")
    problems: list[str] = []
    with warnings.catch_warnings(), pytest.warns(UserWarning, match=r"non-finite pose values .* \(1\)"):
        warnings.simplefilter("error", RuntimeWarning)  # no stray 'invalid value' from the NaN block
        poses = read_poses(folder / "pose.txt", [0, 1, 2], problems)
    assert len(problems) == 1 and "no pose" in problems[0]
    assert np.isnan(poses[1, :3, :3]).all() and (poses[[0, 2], :3, :3] == np.eye(3)).all()


@pytest.mark.parametrize("damage, message", [
    (lambda folder: (folder.parent / "calibration" / "cfhq190l_omnidirectional_values.txt").unlink(),
     "calibration not found"),
    (lambda folder: (folder.parent / "calibration" / "cfhq190l_omnidirectional_values.txt").write_text("1 2 3"),
     "expected 11 finite numbers"),
    (lambda folder: (folder / "0002_depth.tiff").unlink(), "no depth for frames \\[2\\]"),
    (lambda folder: (folder / "pose.txt").write_text("1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1\n"),
     "1 poses for frame numbers up to 2"),
    (lambda folder: (folder / "pose.txt").write_text("1,0,0,5,0,1,0,0,0,0,1,0,0,0,0,1\n" * 3),
     "not column-major"),
    (lambda folder: (folder / "pose.txt").write_text("1,0,0\n" * 3), "line 1: expected 16 comma-separated numbers"),
    # a rotation block scaled by 1.01, and one mirrored: no rotation, whatever the file's rounding
    (lambda folder: (folder / "pose.txt").write_text("1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1\n"
                                                     "1.01,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1\n"
                                                     "-1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1\n"),
     r"the 3x3 block is not a rotation: frame\(s\) 1: R\^T R differs from the identity by up to 0.02 \(at most "
     r"0.0001 expected\); frame\(s\) 2: determinant negative \(a mirror\)"),
])
def test_bad_input_is_refused_naming_the_file(tmp_path: Path, damage, message):
    folder = write_sequence(tmp_path)
    damage(folder)
    with pytest.raises(DataFormatError, match=message):
        open_reader(tmp_path, "c3vd", Params()).sequences()


def test_frames_of_another_size_than_the_calibration_are_refused(tmp_path: Path):
    folder = write_sequence(tmp_path)
    for path in folder.glob("*_color.png"):
        cv2.imwrite(str(path), np.zeros((20, 40, 3), np.uint8))
    with pytest.raises(DataFormatError, match="frames are 40x20, the calibration describes 40x30"):
        open_reader(tmp_path, "c3vd", Params()).sequences()


def test_a_later_frame_of_another_size_is_refused_when_it_is_read(tmp_path: Path):
    folder = write_sequence(tmp_path)
    cv2.imwrite(str(folder / "2_color.png"), np.zeros((20, 40, 3), np.uint8))
    (sequence,) = open_reader(tmp_path, "c3vd", Params()).sequences()
    sequence.load_rgb(1)
    with pytest.raises(DataFormatError, match=r"2_color.png.*image size \(20, 40\) differs from the sequence's"):
        sequence.load_rgb(2)


@needs_sample
def test_the_calibration_centre_counted_from_pixel_1_lands_near_the_image_centre():
    camera = read_calibration(C3VD_SAMPLE / "calibration" / "cfhq190l_omnidirectional_values.txt")
    # the file's 679.54 and 543.98 are MATLAB's, counted from 1
    assert (camera.cx, camera.cy) == pytest.approx((678.5448, 542.9759), abs=1e-4)


@needs_sample
def test_a_copy_of_the_sample_without_its_calibration_names_what_to_set(tmp_path: Path):
    shutil.copytree(SEQUENCE, tmp_path / "cecum_t1_a", ignore=shutil.ignore_patterns("*_color.png", "*.tiff"))
    with pytest.raises(DataFormatError, match="set data.c3vd.calibration"):
        open_reader(tmp_path, "c3vd", Params()).sequences()

"""EndoSLAM reader: UnityCam (incl. pose rows that do not match frames) and real-camera layouts."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from endoflow.config import EndoSLAMConfig
from endoflow.data.endoslam import EndoSLAMReader, slerp_xyzw
from endoflow.data.imageio import write_png
from endoflow.errors import DataFormatError
from tests.fixtures_native import (
    FLIP_Y,
    quaternion_xyzw,
    rotation,
    write_endoslam_camera,
    write_endoslam_unitycam,
)

CAMERA_K = [[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]]


def _only(root, cfg=None):
    (sequence,) = EndoSLAMReader(root, cfg or EndoSLAMConfig()).sequences()
    return sequence


# ------------------------------------------------------------------------------------- UnityCam
def test_unitycam_round_trip_when_rows_match_frames(tmp_path):
    truth = write_endoslam_unitycam(tmp_path, organ="Small Intestine", frames=5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean log must not warn
        sequence = _only(tmp_path)
    assert (sequence.name, sequence.group, sequence.split) == ("UnityCam/Small Intestine", "Small Intestine", "test")
    assert sequence.problems == []
    np.testing.assert_allclose(sequence.poses, truth.T_world_cam, atol=1e-12)
    np.testing.assert_allclose(sequence.K, truth.K, rtol=1e-12)
    for i in range(len(sequence)):
        np.testing.assert_array_equal(sequence.load_rgb(i), truth.rgb[i])
        np.testing.assert_allclose(sequence.load_depth(i), truth.depth_cm[i], rtol=1e-6)


def test_unitycam_default_K_is_the_documented_one_scaled_to_the_stored_size(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=1, size=160)
    K = _only(tmp_path).K
    np.testing.assert_allclose(K[0], [156.0418 / 2, 0, (178.5604 + 0.5) / 2 - 0.5])
    np.testing.assert_allclose(K[1], [0, 155.7529 / 2, (181.8043 + 0.5) / 2 - 0.5])


def test_unitycam_mismatched_rows_are_aligned_by_time_with_a_warning(tmp_path):
    truth = write_endoslam_unitycam(tmp_path, frames=8, matched=False)
    with pytest.warns(UserWarning) as caught:
        sequence = _only(tmp_path)
    warned = " | ".join(str(w.message) for w in caught)
    notes = " | ".join(sequence.problems)
    for text in ("dropped 1 row(s) with missing values", "7 pose rows for 8 frames; aligned by time",
                 "3 frame(s) after the last logged time have no pose"):
        assert text in warned and text in notes
    np.testing.assert_allclose(sequence.poses[:5], truth.T_world_cam[:5], atol=1e-9)
    assert np.isnan(sequence.poses[5:]).all()
    assert [sequence.pose(i) is None for i in range(8)] == [False] * 5 + [True] * 3


def test_unitycam_units_and_depth_scale_come_from_params(tmp_path):
    truth = write_endoslam_unitycam(tmp_path, frames=3, depth_full_scale_cm=8.0)
    cfg = EndoSLAMConfig().replace(unitycam_translation_to_cm=10.0, depth_full_scale_cm=8.0)
    sequence = _only(tmp_path, cfg)
    np.testing.assert_allclose(sequence.poses[:, :3, 3], 10 * truth.T_world_cam[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(sequence.poses[:, :3, :3], truth.T_world_cam[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(sequence.load_depth(2), truth.depth_cm[2], rtol=1e-6)


def test_unitycam_ray_length_depth_becomes_z_depth(tmp_path):
    truth = write_endoslam_unitycam(tmp_path, frames=1, size=32)
    cfg = EndoSLAMConfig().replace(depth_is_ray_length=True, intrinsics=[[20.0, 0, 15.5], [0, 20.0, 15.5], [0, 0, 1]])
    depth = _only(tmp_path, cfg).load_depth(0)
    v, u = np.mgrid[0:32, 0:32]
    ray_norm = np.sqrt(((u - 15.5) / 20.0) ** 2 + ((v - 15.5) / 20.0) ** 2 + 1)
    np.testing.assert_allclose(depth, truth.depth_cm[0] / ray_norm, rtol=1e-6)


def test_unitycam_camera_looks_along_plus_z_after_conversion(tmp_path):
    """A Unity camera-to-world with identity rotation looks along world +z; so must ours (y flipped)."""
    write_endoslam_unitycam(tmp_path, frames=2)
    csv = tmp_path / "UnityCam" / "Colon" / "Poses" / "colon_position_rotation.csv"
    csv.write_text("tX,tY,tZ,rX,rY,rZ,rW,time(s)\n1,2,3,0,0,0,1,0\n1,2,3,0,0,0,-1,0.033\n")
    sequence = _only(tmp_path)
    np.testing.assert_allclose(sequence.poses[0], [[1, 0, 0, 1], [0, 1, 0, -2], [0, 0, 1, 3], [0, 0, 0, 1]])
    np.testing.assert_allclose(sequence.poses[1], sequence.poses[0])


def test_slerp_takes_the_shorter_arc_and_hits_the_midpoint():
    q0 = quaternion_xyzw(rotation((0, 0, 1), 0.2))
    q1 = -quaternion_xyzw(rotation((0, 0, 1), 0.6))  # sign-flipped: the same rotation
    middle = slerp_xyzw(q0[None], q1[None], np.array([0.5]))[0]
    np.testing.assert_allclose(np.abs(middle), np.abs(quaternion_xyzw(rotation((0, 0, 1), 0.4))), atol=1e-12)


def test_unitycam_depth_with_unequal_channels_is_rejected(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=2)
    depth = tmp_path / "UnityCam" / "Colon" / "Pixelwise Depths" / "aov_image_0001.png"
    write_png(depth, np.dstack([np.full((32, 32), v, np.uint8) for v in (10, 20, 30)]))
    sequence = _only(tmp_path)
    with pytest.raises(DataFormatError, match="equal colour channels") as info:
        sequence.load_depth(1)
    assert info.value.path == depth


def test_unitycam_missing_depth_image(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=3)
    depth = tmp_path / "UnityCam" / "Colon" / "Pixelwise Depths" / "aov_image_0002.png"
    depth.unlink()
    with pytest.raises(DataFormatError, match="missing image: depth map for image_0002.png") as info:
        EndoSLAMReader(tmp_path, EndoSLAMConfig()).sequences()
    assert info.value.path == depth


def test_unitycam_csv_without_the_expected_header(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=2)
    csv = tmp_path / "UnityCam" / "Colon" / "Poses" / "colon_position_rotation.csv"
    csv.write_text("x,y,z,qx,qy,qz,qw,t\n0,0,0,0,0,0,1,0\n")
    with pytest.raises(DataFormatError, match=r"expected columns tX, tY, tZ, rX, rY, rZ, rW, time\(s\)") as info:
        EndoSLAMReader(tmp_path, EndoSLAMConfig()).sequences()
    assert info.value.path == csv


def test_unitycam_missing_pose_file(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=2)
    poses = tmp_path / "UnityCam" / "Colon" / "Poses"
    (poses / "colon_position_rotation.csv").unlink()
    with pytest.raises(DataFormatError, match=r"expected exactly one pose file \*_position_rotation.csv, found none"):
        EndoSLAMReader(tmp_path, EndoSLAMConfig()).sequences()


def test_unitycam_empty_sequence(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=1)
    frame = tmp_path / "UnityCam" / "Colon" / "Frames" / "image_0000.png"
    frame.unlink()
    with pytest.raises(DataFormatError, match="empty sequence") as info:
        EndoSLAMReader(tmp_path, EndoSLAMConfig()).sequences()
    assert info.value.path == frame.parent


def test_calibration_folder_is_not_a_sequence(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=2)
    (tmp_path / "UnityCam" / "Calibration").mkdir()
    assert [s.name for s in EndoSLAMReader(tmp_path, EndoSLAMConfig()).sequences()] == ["UnityCam/Colon"]


# --------------------------------------------------------------------------------- real cameras
def test_camera_layout_joins_poses_on_image_frame(tmp_path):
    truth = write_endoslam_camera(tmp_path, frames=4)
    cfg = EndoSLAMConfig().replace(intrinsics=CAMERA_K, split="val")
    with pytest.warns(UserWarning, match="1 of 4 frames have no pose row"):
        sequence = _only(tmp_path, cfg)
    assert (sequence.name, sequence.group, sequence.split) == ("HighCam/Colon-IV/TumorfreeTrajectory_1", "Colon", "val")
    assert sequence.image_size == (24, 32) and sequence.load_depth is None
    np.testing.assert_array_equal(sequence.K, CAMERA_K)
    np.testing.assert_allclose(sequence.poses[:3], truth.T_world_cam[:3], atol=1e-12)  # metres -> cm
    assert sequence.pose(3) is None
    rgb = sequence.load_rgb(1)
    assert rgb.dtype == np.uint8 and np.abs(rgb.astype(int) - truth.rgb[1]).max() <= 4  # JPEG


def test_camera_poses_left_handed_are_converted(tmp_path):
    truth = write_endoslam_camera(tmp_path, frames=3)
    cfg = EndoSLAMConfig().replace(intrinsics=CAMERA_K, camera_poses_left_handed=True)
    with pytest.warns(UserWarning):
        sequence = _only(tmp_path, cfg)
    np.testing.assert_allclose(sequence.poses[:2], FLIP_Y @ truth.T_world_cam[:2] @ FLIP_Y, atol=1e-12)


def test_camera_layout_needs_intrinsics_from_params(tmp_path):
    write_endoslam_camera(tmp_path, frames=2)
    trajectory = tmp_path / "Cameras" / "HighCam" / "Colon-IV" / "TumorfreeTrajectory_1"
    with pytest.raises(DataFormatError, match="set data.endoslam.intrinsics") as info:
        EndoSLAMReader(tmp_path, EndoSLAMConfig()).sequences()
    assert info.value.path == trajectory


def test_camera_sheet_with_missing_columns(tmp_path):
    columns = ["ImageFrame", "Pose_Index", "x", "y", "z", "quot_x", "quot_y", "quot_z", "quot_w"]
    write_endoslam_camera(tmp_path, frames=2, columns=columns)
    sheet = tmp_path / "Cameras" / "HighCam" / "Colon-IV" / "TumorfreeTrajectory_1" / "Poses" / "poses.xlsx"
    cfg = EndoSLAMConfig().replace(intrinsics=CAMERA_K)
    expected = "expected columns ImageFrame, Pose_Index, trans_x.*; missing trans_x, trans_y, trans_z"
    with pytest.raises(DataFormatError, match=expected) as info:
        EndoSLAMReader(tmp_path, cfg).sequences()
    assert info.value.path == sheet


def test_layout_param_selects_one_layout(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=2)
    write_endoslam_camera(tmp_path, frames=2)
    unity_only = EndoSLAMReader(tmp_path, EndoSLAMConfig().replace(layout="unitycam")).sequences()
    assert [s.name for s in unity_only] == ["UnityCam/Colon"]
    cfg = EndoSLAMConfig().replace(layout="auto", intrinsics=CAMERA_K)
    with pytest.warns(UserWarning):
        both = EndoSLAMReader(tmp_path, cfg).sequences()
    assert [s.name for s in both] == ["HighCam/Colon-IV/TumorfreeTrajectory_1", "UnityCam/Colon"]


def test_requested_layout_missing(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=2)
    with pytest.raises(DataFormatError, match="folder not found") as info:
        EndoSLAMReader(tmp_path, EndoSLAMConfig().replace(layout="camera")).sequences()
    assert info.value.path == tmp_path / "Cameras"

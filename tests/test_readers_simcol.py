"""SimCol3D reader: the real sample files, native-layout fixtures, and every documented bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from endoflow.config import SimColConfig
from endoflow.data.imageio import write_png
from endoflow.data.simcol import SimColReader
from endoflow.errors import DataFormatError
from tests.fixtures_native import SIMCOL_K_475, scaled_K, write_simcol
from tests.samples import SIMCOL_SAMPLE

needs_sample = pytest.mark.skipif(
    not (SIMCOL_SAMPLE / "SyntheticColon_I").is_dir(), reason=f"real SimCol3D sample not found at {SIMCOL_SAMPLE}"
)


@pytest.fixture(scope="module")
def sample_sequence():
    (sequence,) = SimColReader(SIMCOL_SAMPLE, SimColConfig()).sequences()
    return sequence


# ------------------------------------------------------------------------------------ real sample
@needs_sample
def test_real_sample_poses_equal_the_official_conversion(sample_sequence):
    official = np.loadtxt(SIMCOL_SAMPLE / "S1_first10_converted_kitti3x4.txt").reshape(-1, 3, 4)
    assert sample_sequence.poses.shape == (10, 4, 4)
    np.testing.assert_allclose(sample_sequence.poses[:, :3, :], official, atol=1e-6)
    np.testing.assert_array_equal(sample_sequence.poses[:, 3, :], np.tile([0, 0, 0, 1], (10, 1)))


@needs_sample
def test_real_sample_camera_moves_forward_along_its_z_axis(sample_sequence):
    first, last = sample_sequence.poses[0], sample_sequence.poses[-1]
    motion_in_first_camera = first[:3, :3].T @ (last[:3, 3] - first[:3, 3])
    assert motion_in_first_camera[2] > 0.5 * np.linalg.norm(motion_in_first_camera)


@needs_sample
def test_real_sample_K_is_cam_txt_read_literally(sample_sequence):
    expected = [[227.60416, 0, 227.60416], [0, 237.5, 237.5], [0, 0, 1]]
    np.testing.assert_array_equal(sample_sequence.K, expected)
    assert sample_sequence.image_size == (475, 475)


@needs_sample
def test_real_sample_rgb_is_the_8bit_values_in_rgb_order(sample_sequence):
    raw = cv2.imread(str(SIMCOL_SAMPLE / "SyntheticColon_I" / "Frames_S1" / "FrameBuffer_0003.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (475, 475, 4) and not (raw % 256).any()
    rgb = sample_sequence.load_rgb(3)
    assert rgb.dtype == np.uint8 and rgb.shape == (475, 475, 3)
    np.testing.assert_array_equal(rgb, raw[..., 2::-1] // 256)
    assert rgb[..., 0].mean() > rgb[..., 2].mean()  # mucosa is red-orange, not blue


@needs_sample
def test_real_sample_depth_in_cm_on_the_20cm_scale(sample_sequence):
    depths = [sample_sequence.load_depth(i) for i in range(len(sample_sequence))]
    assert all(d.dtype == np.float32 and d.shape == (475, 475) for d in depths)
    assert min(d.min() for d in depths) == pytest.approx(0.63, abs=0.01)
    assert max(d.max() for d in depths) == pytest.approx(13.33, abs=0.01)


@needs_sample
def test_real_sample_split_group_and_frames(sample_sequence):
    assert (sample_sequence.name, sample_sequence.split, sample_sequence.group) == ("S1", "train", "SyntheticColon_I")
    assert sample_sequence.frame_ids == list(range(10))
    assert sample_sequence.problems == []


# ------------------------------------------------------------------------------------- fixtures
@pytest.fixture()
def simcol(tmp_path):
    return tmp_path, write_simcol(tmp_path)


def test_fixture_round_trip_poses_rgb_depth_and_K(simcol):
    root, expected = simcol
    sequences = SimColReader(root, SimColConfig()).sequences()
    assert [s.name for s in sequences] == ["O1", "S1", "S4"]
    for sequence in sequences:
        truth = expected[sequence.name]
        assert (sequence.split, sequence.group, sequence.frame_ids) == (truth.split, truth.group, truth.frame_ids)
        np.testing.assert_allclose(sequence.poses, truth.T_world_cam, atol=1e-12)
        np.testing.assert_allclose(sequence.K, truth.K, rtol=1e-12)
        for i in range(len(sequence)):
            frame = sequence.frame(i)
            np.testing.assert_array_equal(frame.rgb, truth.rgb[i])
            np.testing.assert_allclose(frame.depth_cm, truth.depth_cm[i], rtol=1e-6)


def test_splits_follow_the_config_lists(simcol):
    root, _ = simcol
    cfg = SimColConfig().replace(val=["S1"], test=["S4"])
    splits = {s.name: s.split for s in SimColReader(root, cfg).sequences()}
    assert splits == {"S1": "val", "S4": "test", "O1": "train"}


def test_sequences_sorted_by_number_not_text(tmp_path):
    write_simcol(tmp_path, scenes={"SyntheticColon_I": ("S10", "S2")}, frames=1, size=8)
    assert [s.name for s in SimColReader(tmp_path, SimColConfig()).sequences()] == ["S2", "S10"]


def test_K_scaled_by_stored_width_over_reference_size(simcol):
    root, _ = simcol
    cfg = SimColConfig().replace(reference_size=64)
    K = SimColReader(root, cfg).sequences()[0].K
    np.testing.assert_allclose(K, scaled_K(SIMCOL_K_475, 0.5, 0.5))
    assert K[0, 0] == pytest.approx(227.60416 / 2) and K[0, 2] == pytest.approx(227.60416 / 2 - 0.25)


def test_intrinsics_param_overrides_cam_txt(simcol):
    root, _ = simcol
    (root / "SyntheticColon_I" / "cam.txt").unlink()
    override = [[200.0, 0.0, 237.0], [0.0, 210.0, 237.0], [0.0, 0.0, 1.0]]
    cfg = SimColConfig().replace(intrinsics=override, reference_size=32)
    for sequence in SimColReader(root, cfg).sequences():
        np.testing.assert_array_equal(sequence.K, override)


# ----------------------------------------------------------------------------------- bad inputs
def _sequence(root: Path, name: str):
    return next(s for s in SimColReader(root, SimColConfig()).sequences() if s.name == name)


def _raises(match: str, path: Path, call):
    with pytest.raises(DataFormatError, match=match) as info:
        call()
    assert info.value.path == path
    assert str(path) in str(info.value)


def test_missing_depth_image(simcol):
    root, _ = simcol
    depth = root / "SyntheticColon_I" / "Frames_S1" / "Depth_0001.png"
    depth.unlink()
    _raises("missing image", depth, lambda: SimColReader(root, SimColConfig()).sequences())


def test_unreadable_frame_image(simcol):
    root, _ = simcol
    frame = root / "SyntheticColon_I" / "Frames_S1" / "FrameBuffer_0002.png"
    frame.write_bytes(frame.read_bytes()[:60])  # truncated
    sequence = _sequence(root, "S1")
    _raises("unreadable image", frame, lambda: sequence.load_rgb(2))


def test_frame_deleted_after_listing(simcol):
    root, _ = simcol
    sequence = _sequence(root, "S1")
    frame = root / "SyntheticColon_I" / "Frames_S1" / "FrameBuffer_0000.png"
    frame.unlink()
    _raises("image file not found", frame, lambda: sequence.load_rgb(0))


def test_depth_of_wrong_bit_depth(simcol):
    root, _ = simcol
    depth = root / "SyntheticColon_I" / "Frames_S4" / "Depth_0001.png"
    write_png(depth, np.full((32, 32), 7, np.uint8))
    sequence = _sequence(root, "S4")
    _raises(r"expected a 16-bit single-channel PNG, found uint8 with 1 channel", depth, lambda: sequence.load_depth(1))


def test_pose_file_with_fewer_lines_than_frames(simcol):
    root, _ = simcol
    positions = root / "SyntheticColon_I" / "SavedPosition_S4.txt"
    positions.write_text("".join(positions.read_text().splitlines(keepends=True)[:2]))
    read = SimColReader(root, SimColConfig()).sequences
    _raises(r"pose file too short: 2 lines for 3 frames", positions, read)


def test_pose_line_with_wrong_count(simcol):
    root, _ = simcol
    rotations = root / "SyntheticColon_III" / "SavedRotationQuaternion_O1.txt"
    lines = rotations.read_text().splitlines()
    rotations.write_text("\n".join([lines[0], "0.1 0.2 0.3", *lines[2:]]))
    _raises(r"line 2: expected 4 numbers", rotations, lambda: SimColReader(root, SimColConfig()).sequences())


def test_missing_pose_file(simcol):
    root, _ = simcol
    rotations = root / "SyntheticColon_I" / "SavedRotationQuaternion_S1.txt"
    rotations.unlink()
    _raises("pose file not found", rotations, lambda: SimColReader(root, SimColConfig()).sequences())


@pytest.mark.parametrize(
    "content, problem",
    [
        ("227.60416 0 227.60416 0 237.5 237.5 0 0", "malformed cam.txt: expected 9 numbers"),
        ("227.6 0 227.6 0 237.5 237.5 0 0 one", "malformed cam.txt: expected 9 numbers"),
        ("227.60416 0 0 0 237.5 0 227.60416 237.5 1", r"expected K = \[\[fx, s, cx\]"),  # column-major
    ],
)
def test_malformed_cam_txt(simcol, content, problem):
    root, _ = simcol
    cam = root / "SyntheticColon_I" / "cam.txt"
    cam.write_text(content)
    _raises(problem, cam, lambda: SimColReader(root, SimColConfig()).sequences())


def test_empty_sequence(simcol):
    root, _ = simcol
    folder = root / "SyntheticColon_I" / "Frames_S9"
    folder.mkdir()
    _raises("empty sequence", folder, lambda: SimColReader(root, SimColConfig()).sequences())


def test_root_without_scene_folders(tmp_path):
    _raises("no SimCol3D scene folder", tmp_path, lambda: SimColReader(tmp_path, SimColConfig()).sequences())

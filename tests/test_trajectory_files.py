"""Camera-path files (TUM, KITTI, SimCol3D challenge relative poses): what they hold and what they refuse."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from endoflow.data.trajectory_files import (
    ROTATION_TOLERANCE,
    kitti_sidecar_path,
    read_kitti,
    read_simcol_relative_poses,
    read_tum,
    simcol_pose_name,
    write_kitti,
    write_simcol_relative_pose,
    write_simcol_relative_poses,
    write_tum,
)
from endoflow.errors import DataFormatError


# ------------------------------------------------------------------------------------------ helpers
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation from the QR decomposition of a Gaussian matrix (independent of endoflow)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_path(count: int, seed: int = 0) -> np.ndarray:
    """``[count, 4, 4]`` rigid camera-to-world poses with translations of tens of cm."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    for pose in poses:
        pose[:3, :3] = random_rotation(rng)
        pose[:3, 3] = rng.normal(scale=30.0, size=3)
    return poses


def rotation_of_quaternion(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Hamilton quaternion (scalar last, unit) to rotation matrix, written out here as an independent check."""
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def pose_lines(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if line and not line.startswith("#")]


def timestamps_for(count: int) -> np.ndarray:
    return 1305031102.175304 + np.arange(count) / 30.0


# ---------------------------------------------------------------------------------------------- TUM
def test_tum_round_trip_gives_back_timestamps_exactly_and_poses_to_1e_12(tmp_path: Path):
    poses, stamps = random_path(50), timestamps_for(50)
    write_tum(tmp_path / "path.tum", stamps, poses)
    read_stamps, read_poses = read_tum(tmp_path / "path.tum")
    np.testing.assert_array_equal(read_stamps, stamps)
    np.testing.assert_array_equal(read_poses[:, :3, 3], poses[:, :3, 3])  # written digits are exact
    np.testing.assert_allclose(read_poses, poses, rtol=0, atol=1e-12)  # through the quaternion


def test_tum_lines_are_timestamp_translation_and_unit_quaternion_scalar_last(tmp_path: Path):
    w, x, y, z = 0.8, 0.2, -0.4, 0.4  # unit norm
    pose = np.eye(4)
    pose[:3, :3] = rotation_of_quaternion(x, y, z, w)
    pose[:3, 3] = (1.5, -2.25, 30.0)
    write_tum(tmp_path / "one.tum", np.array([12.5]), pose[None])
    values = np.array(pose_lines(tmp_path / "one.tum")[0].split(), dtype=np.float64)
    np.testing.assert_allclose(values, [12.5, 1.5, -2.25, 30.0, x, y, z, w], atol=1e-15)


def test_tum_quaternions_are_written_with_non_negative_scalar(tmp_path: Path):
    # q and -q are the same rotation; the file picks qw >= 0, so a given rotation has one text
    x, y, z, w = 0.1, 0.2, 0.3, -np.sqrt(1 - 0.14)
    pose = np.eye(4)
    pose[:3, :3] = rotation_of_quaternion(x, y, z, w)
    poses = np.concatenate([pose[None], random_path(40, seed=3)])
    write_tum(tmp_path / "signs.tum", timestamps_for(41), poses)
    quaternions = np.array([line.split()[4:] for line in pose_lines(tmp_path / "signs.tum")], dtype=np.float64)
    assert np.all(quaternions[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(quaternions, axis=1), 1, atol=1e-15)
    np.testing.assert_allclose(quaternions[0], [-x, -y, -z, -w], atol=1e-15)


def test_tum_header_comments_state_the_pose_convention_and_units(tmp_path: Path):
    write_tum(tmp_path / "path.tum", timestamps_for(3), random_path(3))
    lines = (tmp_path / "path.tum").read_text().splitlines()
    header = [line for line in lines if line.startswith("#")]
    assert lines[: len(header)] == header and len(lines) == len(header) + 3  # header first, then one per pose
    text = "\n".join(header)
    for stated in ("timestamp tx ty tz qx qy qz qw", "camera-to-world T_world_cam", "OpenCV",
                   "timestamp in s", "translation in cm", "scalar last", "qw >= 0"):
        assert stated in text


def test_tum_reader_skips_comments_and_blank_lines_and_normalises_rounded_quaternions(tmp_path: Path):
    path = tmp_path / "other_tool.txt"
    path.write_text("# ground truth\n\n1.0 0 0 0 0 0 0 1\n2.0 1 2 3 0.0 0.0 0.70711 0.70711\n")
    stamps, poses = read_tum(path)
    np.testing.assert_array_equal(stamps, [1.0, 2.0])
    np.testing.assert_allclose(poses[1], [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], atol=1e-12)


# -------------------------------------------------------------------------------------------- KITTI
def test_kitti_round_trip_gives_back_the_poses_bit_for_bit(tmp_path: Path):
    poses = random_path(50, seed=1)
    write_kitti(tmp_path / "path.txt", poses)
    np.testing.assert_array_equal(read_kitti(tmp_path / "path.txt"), poses)


def test_kitti_lines_are_the_top_3x4_row_major_with_no_header(tmp_path: Path):
    poses = random_path(4, seed=2)
    write_kitti(tmp_path / "path.txt", poses)
    lines = (tmp_path / "path.txt").read_text().splitlines()
    assert len(lines) == 4
    np.testing.assert_array_equal(np.array([line.split() for line in lines], dtype=np.float64),
                                  poses[:, :3, :].reshape(4, 12))


def test_kitti_convention_is_stated_in_a_sidecar_json_beside_the_file(tmp_path: Path):
    write_kitti(tmp_path / "path.txt", random_path(7))
    sidecar = kitti_sidecar_path(tmp_path / "path.txt")
    assert sidecar == tmp_path / "path.txt.json"
    stated = json.loads(sidecar.read_text())
    assert stated["file"] == "path.txt" and stated["poses"] == 7
    assert stated["translation_unit"] == "cm"
    assert "camera-to-world T_world_cam" in stated["pose"] and "row-major" in stated["pose"]
    assert "OpenCV" in stated["camera"] and "z forward" in stated["camera"]


# ----------------------------------------------------------------------------------------- SimCol3D
def test_simcol_relative_pose_file_has_the_challenge_name_and_one_line_of_16_numbers(tmp_path: Path):
    relative = random_path(1, seed=4)[0]
    path = write_simcol_relative_pose(tmp_path / "Frames_S5_OP", 7, 8, relative)
    assert path == tmp_path / "Frames_S5_OP" / "pose" / "FrameBuffer_0007_to_FrameBuffer_0008.txt"
    lines = path.read_text().splitlines()
    assert len(lines) == 1 and lines[0].split()[12:] == ["0", "0", "0", "1"]
    np.testing.assert_allclose(np.array(lines[0].split(), dtype=np.float64).reshape(4, 4), relative,
                               rtol=1e-8, atol=1e-9)


def test_simcol_relative_pose_bytes_are_what_evaluation_always_wrote(tmp_path: Path):
    relative = random_path(1, seed=5)[0]
    relative[3] = (0.0, 0.0, 1e-9, 1.0)  # within tolerance of rigid: written as exactly 0 0 0 1
    path = write_simcol_relative_pose(tmp_path, 0, 1, relative, durable=False)
    exact = relative.copy()
    exact[3] = (0.0, 0.0, 0.0, 1.0)
    assert path.read_text() == " ".join(f"{v:.9g}" for v in exact.reshape(-1)) + "\n"


def test_simcol_path_files_hold_inv_p_i_times_p_next_for_each_consecutive_pair(tmp_path: Path):
    poses, frames = random_path(6, seed=6), np.array([0, 1, 2, 4, 5, 6])
    paths = write_simcol_relative_poses(tmp_path / "seq", frames, poses)
    assert [p.name for p in paths] == [simcol_pose_name(a, b) for a, b in zip(frames[:-1], frames[1:])]
    assert sorted(p.name for p in (tmp_path / "seq" / "pose").iterdir()) == [p.name for p in paths]
    pairs, relative = read_simcol_relative_poses(tmp_path / "seq")
    assert pairs == [(0, 1), (1, 2), (2, 4), (4, 5), (5, 6)]
    expected = np.linalg.inv(poses[:-1]) @ poses[1:]
    np.testing.assert_allclose(relative, expected, rtol=0, atol=1e-7)  # 9 digits of numbers below ~100 cm


def test_simcol_path_replaces_the_pose_folder_whole(tmp_path: Path):
    write_simcol_relative_poses(tmp_path, np.arange(5), random_path(5))
    write_simcol_relative_poses(tmp_path, np.arange(3), random_path(3))
    assert sorted(p.name for p in (tmp_path / "pose").iterdir()) == [simcol_pose_name(0, 1), simcol_pose_name(1, 2)]


def test_simcol_reader_sorts_by_file_name_and_skips_hidden_temporaries(tmp_path: Path):
    poses = random_path(3, seed=7)
    for earlier in (12, 3, 7):  # written out of order
        write_simcol_relative_pose(tmp_path, earlier, earlier + 1, poses[earlier % 3])
    (tmp_path / "pose" / ".FrameBuffer_0001_to_FrameBuffer_0002.txt.tmp-x").write_text("half")
    pairs, relative = read_simcol_relative_poses(tmp_path)
    assert pairs == [(3, 4), (7, 8), (12, 13)]
    np.testing.assert_allclose(relative, poses[[0, 1, 0]], rtol=1e-8, atol=1e-9)


# ------------------------------------------------------------------------------------ independent: evo
def test_evo_reads_our_tum_file_as_the_same_timestamps_and_poses(tmp_path: Path):
    from evo.tools import file_interface

    poses, stamps = random_path(20, seed=8), timestamps_for(20)
    write_tum(tmp_path / "path.tum", stamps, poses)
    trajectory = file_interface.read_tum_trajectory_file(str(tmp_path / "path.tum"))
    np.testing.assert_array_equal(trajectory.timestamps, stamps)
    np.testing.assert_allclose(np.stack(trajectory.poses_se3), poses, rtol=0, atol=1e-12)


def test_evo_reads_our_kitti_file_as_the_same_poses(tmp_path: Path):
    from evo.tools import file_interface

    poses = random_path(20, seed=9)
    write_kitti(tmp_path / "path.txt", poses)
    trajectory = file_interface.read_kitti_poses_file(str(tmp_path / "path.txt"))
    np.testing.assert_array_equal(np.stack(trajectory.poses_se3), poses)


# ---------------------------------------------------------------------------------- bad input: writers
def bent(kind: str) -> np.ndarray:
    """A 3-pose path whose pose 2 is wrong in one way."""
    poses = random_path(3, seed=10)
    if kind == "nan":
        poses[2, 1, 3] = np.nan
    elif kind == "inf":
        poses[2, 0, 0] = np.inf
    elif kind == "scaled":
        poses[2, :3, :3] *= 1 + 10 * ROTATION_TOLERANCE
    elif kind == "sheared":
        poses[2, 0, 1] += 10 * ROTATION_TOLERANCE
    elif kind == "reflection":
        poses[2, :3, 0] *= -1
    elif kind == "last row":
        poses[2, 3] = (0.0, 0.1, 0.0, 1.0)
    return poses


WRITERS: dict[str, Callable[[Path, np.ndarray], None]] = {
    "tum": lambda path, poses: write_tum(path, timestamps_for(len(poses)), poses),
    "kitti": write_kitti,
    "simcol path": lambda path, poses: write_simcol_relative_poses(path, np.arange(len(poses)), poses),
}
PROBLEMS = {"nan": "non-finite", "inf": "non-finite", "scaled": "not orthonormal", "sheared": "not orthonormal",
            "reflection": "reflection", "last row": "last row"}


@pytest.mark.parametrize("writer", WRITERS)
@pytest.mark.parametrize("kind", PROBLEMS)
def test_writers_refuse_a_non_rigid_or_non_finite_pose_naming_file_and_line(tmp_path: Path, writer: str,
                                                                             kind: str):
    target = tmp_path / "out"
    with pytest.raises(DataFormatError, match=f"pose 2 \\(line 3\\): expected a finite rigid .*{PROBLEMS[kind]}") \
            as raised:
        WRITERS[writer](target, bent(kind))
    assert str(target) in str(raised.value)
    assert list(tmp_path.iterdir()) == []  # refused before anything is written


@pytest.mark.parametrize("writer", WRITERS)
@pytest.mark.parametrize("shape", [(3, 3, 4), (3, 4), (0, 4, 4), (2, 4, 4, 1)])
def test_writers_refuse_poses_of_the_wrong_shape(tmp_path: Path, writer: str, shape: tuple[int, ...]):
    poses = np.zeros(shape)
    with pytest.raises(DataFormatError, match=r"expected poses of shape \[N, 4, 4\]"):
        WRITERS[writer](tmp_path / "out", poses)


def test_simcol_pose_writer_refuses_a_non_rigid_pose_or_a_wrong_shape_or_frame_order(tmp_path: Path):
    with pytest.raises(DataFormatError, match="FrameBuffer_0001_to_FrameBuffer_0002.txt: pose: .*orthonormal"):
        write_simcol_relative_pose(tmp_path, 1, 2, bent("scaled")[2])
    with pytest.raises(DataFormatError, match=r"expected a \[4, 4\] pose .*got shape \(3, 4\)"):
        write_simcol_relative_pose(tmp_path, 1, 2, np.eye(4)[:3])
    with pytest.raises(DataFormatError, match="earlier < later, got 2 and 2"):
        write_simcol_relative_pose(tmp_path, 2, 2, np.eye(4))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("stamps, problem", [
    (np.arange(2.0), r"expected timestamps of shape \[3\]"),
    (np.array([0.0, np.nan, 2.0]), r"timestamp 1 \(line 2\): expected a finite number"),
    (np.array([0.0, 1.0, 1.0]), "line 3: expected timestamps increasing strictly"),
])
def test_tum_writer_refuses_bad_timestamps(tmp_path: Path, stamps: np.ndarray, problem: str):
    with pytest.raises(DataFormatError, match=problem):
        write_tum(tmp_path / "path.tum", stamps, random_path(3))


@pytest.mark.parametrize("frames, problem", [
    (np.array([0, 1]), r"expected \[N >= 2\] integer frame numbers"),
    (np.array([0.0, 1.0, 2.0]), r"expected \[N >= 2\] integer frame numbers"),
    (np.array([0, 2, 1]), "earlier < later, got 2 and 1"),
    (np.array([-1, 0, 1]), "earlier < later, got -1 and 0"),
])
def test_simcol_path_writer_refuses_bad_frame_numbers(tmp_path: Path, frames: np.ndarray, problem: str):
    with pytest.raises(DataFormatError, match=problem):
        write_simcol_relative_poses(tmp_path, frames, random_path(3))


def test_a_refused_write_leaves_the_previous_file_untouched(tmp_path: Path):
    write_kitti(tmp_path / "path.txt", random_path(3))
    before = (tmp_path / "path.txt").read_bytes()
    with pytest.raises(DataFormatError):
        write_kitti(tmp_path / "path.txt", bent("nan"))
    assert (tmp_path / "path.txt").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["path.txt", "path.txt.json"]  # no temporaries


# ---------------------------------------------------------------------------------- bad input: readers
GOOD_TUM = "0.0 0 0 0 0 0 0 1\n"
GOOD_KITTI = "1 0 0 0 0 1 0 0 0 0 1 0\n"


@pytest.mark.parametrize("text, problem", [
    (GOOD_TUM + "1.0 0 0 0 0 0 1\n", r"line 2: expected 8 numbers \(timestamp tx ty tz qx qy qz qw\)"),
    (GOOD_TUM + "1.0 0 0 zero 0 0 0 1\n", "line 2: expected 8 numbers"),
    ("# header\n" + GOOD_TUM + "1.0 0 nan 0 0 0 0 1\n", "line 3: expected finite numbers"),
    (GOOD_TUM + "1.0 0 0 0 0 0 0 2\n", "line 2: expected a unit quaternion"),
    (GOOD_TUM + GOOD_TUM, "line 2: expected timestamps increasing strictly"),
    ("# only a header\n", "no poses"),
])
def test_tum_reader_refuses_bad_lines_naming_file_and_line(tmp_path: Path, text: str, problem: str):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(DataFormatError, match=problem) as raised:
        read_tum(path)
    assert raised.value.path == path


@pytest.mark.parametrize("text, problem", [
    (GOOD_KITTI + "1 0 0 0 0 1 0 0 0 0 1\n", r"line 2: expected 12 numbers \(r11 r12 r13 tx"),
    (GOOD_KITTI + "# comment\n", "line 2: expected 12 numbers"),
    (GOOD_KITTI + "1 0 0 0 0 1 0 0 0 0 1 inf\n", "line 2: expected finite numbers"),
    (GOOD_KITTI + "2 0 0 0 0 1 0 0 0 0 1 0\n", "line 2: expected a finite rigid .* not orthonormal"),
    (GOOD_KITTI + "-1 0 0 0 0 1 0 0 0 0 1 0\n", "line 2: expected a finite rigid .* reflection"),
    ("", "no poses"),
])
def test_kitti_reader_refuses_bad_lines_naming_file_and_line(tmp_path: Path, text: str, problem: str):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(DataFormatError, match=problem) as raised:
        read_kitti(path)
    assert raised.value.path == path


def test_readers_refuse_a_missing_or_non_text_file_naming_it(tmp_path: Path):
    with pytest.raises(DataFormatError, match="missing.tum: file not found"):
        read_tum(tmp_path / "missing.tum")
    (tmp_path / "binary.txt").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(DataFormatError, match="binary.txt: not UTF-8 text"):
        read_kitti(tmp_path / "binary.txt")


IDENTITY_16 = "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"


@pytest.mark.parametrize("name, text, problem", [
    ("FrameBuffer_0000_to_FrameBuffer_0001.txt", IDENTITY_16 + "\n" + IDENTITY_16 + "\n",
     "line 2: expected one line of 16 numbers, found 2 lines"),
    ("FrameBuffer_0000_to_FrameBuffer_0001.txt", IDENTITY_16[:-2] + "\n", "line 1: expected 16 numbers"),
    ("FrameBuffer_0000_to_FrameBuffer_0001.txt", IDENTITY_16.replace("1 0 0 0 0 1", "1 0 0 0 0 3", 1),
     "line 1: expected a finite rigid .* not orthonormal"),
    ("FrameBuffer_0000_to_FrameBuffer_0001.txt", IDENTITY_16[:-1] + "0", "line 1: .* last row"),
    ("FrameBuffer_0000_to_FrameBuffer_0001.txt", IDENTITY_16.replace("0", "nan", 1), "line 1: expected finite"),
    ("notes.txt", IDENTITY_16, "notes.txt: expected a file named FrameBuffer_XXXX_to_FrameBuffer_YYYY.txt"),
    ("FrameBuffer_0005_to_FrameBuffer_0004.txt", IDENTITY_16, "earlier < later, got 5 and 4"),
])
def test_simcol_reader_refuses_bad_files_naming_them(tmp_path: Path, name: str, text: str, problem: str):
    (tmp_path / "pose").mkdir()
    (tmp_path / "pose" / name).write_text(text)
    with pytest.raises(DataFormatError, match=problem) as raised:
        read_simcol_relative_poses(tmp_path)
    assert raised.value.path == tmp_path / "pose" / name


def test_simcol_reader_refuses_a_missing_or_empty_pose_folder(tmp_path: Path):
    with pytest.raises(DataFormatError, match="pose: expected a folder of FrameBuffer_XXXX"):
        read_simcol_relative_poses(tmp_path)
    (tmp_path / "pose").mkdir()
    with pytest.raises(DataFormatError, match="pose: no relative pose files"):
        read_simcol_relative_poses(tmp_path)

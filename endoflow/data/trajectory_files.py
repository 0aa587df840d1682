"""Camera-path files, the one home of their formats: TUM, KITTI and the SimCol3D challenge's relative poses.

Every function takes or returns ``[N, 4, 4]`` float64 ``T_world_cam`` (OpenCV camera, cm) and converts nothing;
writes are atomic, and a bad pose or line raises DataFormatError naming the file and line. See docs/outputs.md,
"Camera-path files".
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from endoflow.errors import DataFormatError
from endoflow.geometry.pose import (matrix_to_quaternion_xyzw, orthonormality_error, quaternion_xyzw_to_matrix,
                                    relative_pose)
from endoflow.io import files_only, staged_directory, write_json, write_text

# Largest |R^T R - I| entry (and |last row - (0, 0, 0, 1)|) accepted as rigid: float32 rotations, such as the
# network's, are orthonormal to about 1e-7; a scaled or sheared matrix is off by far more.
ROTATION_TOLERANCE = 1e-5
# Largest |‖q‖ - 1| accepted when reading a TUM file: files of other tools round quaternions to 4-6 digits.
QUATERNION_NORM_TOLERANCE = 1e-3

TUM_FIELDS = "timestamp tx ty tz qx qy qz qw"
TUM_HEADER = (
    f"# TUM RGB-D trajectory: {TUM_FIELDS}\n"
    "# pose: camera-to-world T_world_cam; camera OpenCV (x right, y down, z forward), right-handed\n"
    "# units: timestamp in s, translation in cm; quaternion unit norm, scalar last, qw >= 0\n"
)
KITTI_FIELDS = "r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz"
SIMCOL_POSE_FOLDER = "pose"
SIMCOL_POSE_NAME = re.compile(r"FrameBuffer_(\d+)_to_FrameBuffer_(\d+)\.txt")
SIMCOL_DIGITS = 9


# ------------------------------------------------------------------------------------------------- TUM
def write_tum(path: str | Path, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write a TUM RGB-D trajectory: ``#`` header lines, then ``timestamp tx ty tz qx qy qz qw`` per pose.

    Args:
        path: the file to write (atomically).
        timestamps: ``[N]`` seconds, finite and strictly increasing.
        poses: ``[N, 4, 4]`` camera-to-world ``T_world_cam``, translation in cm, rigid.
    """
    poses = _checked_poses(path, poses)
    timestamps = _checked_timestamps(path, timestamps, len(poses))
    quaternions = matrix_to_quaternion_xyzw(poses[:, :3, :3])
    lines = [_numbers_text([stamp, *pose[:3, 3], *quaternion])
             for stamp, pose, quaternion in zip(timestamps, poses, quaternions)]
    write_text(path, TUM_HEADER + "".join(line + "\n" for line in lines))


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM RGB-D trajectory: ``([N] timestamps in s, [N, 4, 4] T_world_cam)``.

    Lines starting with ``#`` and blank lines are skipped. Quaternions (scalar last) must have unit norm
    within :data:`QUATERNION_NORM_TOLERANCE` and are normalised; timestamps must increase strictly.
    """
    rows, lines = _number_rows(path, 8, TUM_FIELDS, comments=True)
    timestamps = rows[:, 0]
    norms = np.linalg.norm(rows[:, 4:], axis=1)
    bad_norm = np.flatnonzero(np.abs(norms - 1) > QUATERNION_NORM_TOLERANCE)
    if bad_norm.size:
        first = bad_norm[0]
        raise DataFormatError(path, f"line {lines[first]}: expected a unit quaternion qx qy qz qw, "
                                    f"its norm is {norms[first]:.6g}")
    _check_increasing(path, timestamps, lines)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = quaternion_xyzw_to_matrix(rows[:, 4:])
    poses[:, :3, 3] = rows[:, 1:4]
    return timestamps, poses


# ----------------------------------------------------------------------------------------------- KITTI
def kitti_sidecar_path(path: str | Path) -> Path:
    """The JSON file beside a KITTI pose file that states its convention: ``<path>.json``."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def write_kitti(path: str | Path, poses: np.ndarray) -> None:
    """Write KITTI odometry poses: per pose one line of the top 3 x 4 of ``T_world_cam``, row-major.

    The format has no header, so the convention (camera-to-world, OpenCV camera, translation in cm) is
    written to the sidecar JSON :func:`kitti_sidecar_path` (``<path>.json``) after the poses.

    Args:
        path: the file to write (atomically).
        poses: ``[N, 4, 4]`` camera-to-world ``T_world_cam``, translation in cm, rigid.
    """
    poses = _checked_poses(path, poses)
    write_text(path, "".join(_numbers_text(pose[:3].reshape(-1)) + "\n" for pose in poses))
    write_json(kitti_sidecar_path(path), {
        "format": "KITTI odometry poses",
        "file": Path(path).name,
        "line": KITTI_FIELDS,
        "pose": "camera-to-world T_world_cam: the top 3 x 4 of the 4 x 4 matrix, row-major",
        "camera": "OpenCV: x right, y down, z forward; right-handed",
        "translation_unit": "cm",
        "poses": len(poses),
    })


def read_kitti(path: str | Path) -> np.ndarray:
    """Read KITTI odometry poses: ``[N, 4, 4]`` ``T_world_cam`` (the sidecar JSON is not needed).

    Blank lines are skipped; every other line must hold 12 numbers whose 3 x 3 part is a rotation.
    """
    rows, lines = _number_rows(path, 12, KITTI_FIELDS, comments=False)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    for pose, line in zip(poses, lines):
        _check_rigid(path, pose, f"line {line}")
    return poses


# --------------------------------------------------------------------------------------------- SimCol3D
def simcol_pose_name(earlier_frame: int, later_frame: int) -> str:
    """The challenge's file name of the relative pose from ``earlier_frame`` to ``later_frame``."""
    return f"FrameBuffer_{earlier_frame:04d}_to_FrameBuffer_{later_frame:04d}.txt"


def write_simcol_relative_pose(folder: str | Path, earlier_frame: int, later_frame: int,
                               T_earlier_later: np.ndarray, durable: bool = True) -> Path:
    """Write one challenge relative pose file into ``<folder>/pose/`` and return its path.

    Args:
        folder: the sequence's prediction folder (``.../SyntheticColon_I_Test/Frames_S5_OP``).
        earlier_frame, later_frame: frame numbers, ``0 <= earlier_frame < later_frame``.
        T_earlier_later: ``[4, 4]`` rigid ``inv(P_earlier) @ P_later`` (maps later-camera points into the
            earlier camera's frame), translation in cm. Its last row is written as exactly ``0 0 0 1``.
        durable: fsync the file (:func:`endoflow.io.atomic_path`); pass ``False`` inside a staged folder.
    """
    path = Path(folder) / SIMCOL_POSE_FOLDER / simcol_pose_name(earlier_frame, later_frame)
    _check_frame_pair(path, earlier_frame, later_frame)
    pose = _checked_poses(path, np.asarray(T_earlier_later)[None], single=True)[0]
    write_text(path, _simcol_pose_text(pose), durable)
    return path


def write_simcol_relative_poses(folder: str | Path, frames: np.ndarray, poses: np.ndarray) -> list[Path]:
    """Write a whole path as challenge files: ``<folder>/pose/`` is replaced whole by ``N - 1`` files.

    Args:
        folder: the sequence's prediction folder (``.../SyntheticColon_I_Test/Frames_S5_OP``).
        frames: ``[N]`` frame numbers, strictly increasing, ``N >= 2``; each consecutive pair gets a file.
        poses: ``[N, 4, 4]`` camera-to-world ``T_world_cam`` (cm) of those frames; file ``i`` holds
            ``inv(P_i) @ P_{i+1}``.

    Returns:
        The paths of the files written, in order.
    """
    target = Path(folder) / SIMCOL_POSE_FOLDER
    poses = _checked_poses(target, poses)
    frames = _checked_frames(target, frames, len(poses))
    relative = relative_pose(poses[:-1], poses[1:])
    earlier_output = files_only("a folder of SimCol relative poses", ("FrameBuffer_*_to_FrameBuffer_*.txt",))
    with staged_directory(target, earlier_output) as staging:
        for earlier, later, pose in zip(frames[:-1], frames[1:], relative):
            # the folder swap makes the files visible, so each one needs no fsync of its own
            write_text(staging / simcol_pose_name(earlier, later), _simcol_pose_text(pose), durable=False)
    return [target / simcol_pose_name(earlier, later) for earlier, later in zip(frames[:-1], frames[1:])]


def read_simcol_relative_poses(folder: str | Path) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Read the challenge files of ``<folder>/pose/``, sorted by name as the official evaluation sorts them.

    Returns:
        ``([(earlier_frame, later_frame), ...], [M, 4, 4] T_earlier_later)``, relative poses in cm.
        Hidden files (temporaries of an interrupted write) are skipped; any other file must be named
        ``FrameBuffer_XXXX_to_FrameBuffer_YYYY.txt`` with ``XXXX < YYYY``.
    """
    pose_folder = Path(folder) / SIMCOL_POSE_FOLDER
    if not pose_folder.is_dir():
        raise DataFormatError(pose_folder, "expected a folder of FrameBuffer_XXXX_to_FrameBuffer_YYYY.txt files")
    files = sorted((p for p in pose_folder.iterdir() if not p.name.startswith(".")), key=lambda p: p.name)
    if not files:
        raise DataFormatError(pose_folder, "no relative pose files (FrameBuffer_XXXX_to_FrameBuffer_YYYY.txt)")
    pairs = [_simcol_frame_pair(path) for path in files]
    poses = np.stack([_read_simcol_pose(path) for path in files])
    return pairs, poses


def _simcol_pose_text(pose: np.ndarray) -> str:
    exact = np.array(pose, dtype=np.float64)
    exact[3] = (0.0, 0.0, 0.0, 1.0)  # rigid by definition; the checked input is within tolerance of it
    return " ".join(f"{v:.{SIMCOL_DIGITS}g}" for v in exact.reshape(-1)) + "\n"


def _simcol_frame_pair(path: Path) -> tuple[int, int]:
    match = SIMCOL_POSE_NAME.fullmatch(path.name)
    if match is None:
        raise DataFormatError(path, "expected a file named FrameBuffer_XXXX_to_FrameBuffer_YYYY.txt")
    earlier, later = int(match[1]), int(match[2])
    _check_frame_pair(path, earlier, later)
    return earlier, later


def _read_simcol_pose(path: Path) -> np.ndarray:
    rows, lines = _number_rows(path, 16, "16 numbers: row-major 4 x 4 inv(P_i) @ P_j", comments=False)
    if len(rows) != 1:
        raise DataFormatError(path, f"line {lines[1]}: expected one line of 16 numbers, found {len(rows)} lines")
    pose = rows[0].reshape(4, 4)
    _check_rigid(path, pose, "line 1")
    return pose


# -------------------------------------------------------------------------------------------- checks
def _checked_poses(path: str | Path, poses: np.ndarray, single: bool = False) -> np.ndarray:
    """``poses`` as ``[N >= 1, 4, 4]`` float64, every one finite and rigid; errors name ``path``."""
    array = np.asarray(poses)
    expected = "a [4, 4] pose" if single else "poses of shape [N, 4, 4], N >= 1"
    shape = tuple(array.shape[1:]) if single else tuple(array.shape)
    if array.ndim != 3 or array.shape[1:] != (4, 4) or len(array) == 0:
        raise DataFormatError(path, f"expected {expected} (T_world_cam, cm), got shape {shape}")
    if array.dtype.kind not in "fiu":
        raise DataFormatError(path, f"expected {expected} of real numbers, got dtype {array.dtype}")
    array = array.astype(np.float64)
    for index, pose in enumerate(array):
        _check_rigid(path, pose, "pose" if single else f"pose {index} (line {index + 1})")
    return array


def _check_rigid(path: str | Path, pose: np.ndarray, where: str) -> None:
    problem = _rigidity_problem(pose)
    if problem is not None:
        raise DataFormatError(path, f"{where}: expected a finite rigid 4 x 4 transform, {problem}")


def _rigidity_problem(pose: np.ndarray) -> Optional[str]:
    """Why ``pose`` is not a rigid transform (non-finite, bad last row, non-orthonormal, reflection)."""
    if not np.all(np.isfinite(pose)):
        return "found a non-finite number"
    bottom = np.max(np.abs(pose[3] - (0.0, 0.0, 0.0, 1.0)))
    if bottom > ROTATION_TOLERANCE:
        return f"its last row {pose[3].tolist()} is not 0 0 0 1"
    rotation = pose[:3, :3]
    error = float(orthonormality_error(rotation))
    if error > ROTATION_TOLERANCE:
        return f"its rotation is not orthonormal (max |R^T R - I| = {error:.3g} > {ROTATION_TOLERANCE:g})"
    if np.linalg.det(rotation) < 0:
        return "its rotation is a reflection (det R = -1)"
    return None


def _checked_timestamps(path: str | Path, timestamps: np.ndarray, count: int) -> np.ndarray:
    array = np.asarray(timestamps)
    if array.shape != (count,) or array.dtype.kind not in "fiu":
        raise DataFormatError(path, f"expected timestamps of shape [{count}] (seconds, one per pose), "
                                    f"got shape {array.shape} of {array.dtype}")
    array = array.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(array))
    if bad.size:
        raise DataFormatError(path, f"timestamp {bad[0]} (line {bad[0] + 1}): expected a finite number of "
                                    f"seconds, got {array[bad[0]]}")
    _check_increasing(path, array, list(range(1, count + 1)))
    return array


def _check_increasing(path: str | Path, timestamps: np.ndarray, lines: list[int]) -> None:
    # a camera path is a function of time: a repeated or earlier timestamp makes it ambiguous
    bad = np.flatnonzero(np.diff(timestamps) <= 0)
    if bad.size:
        line = lines[bad[0] + 1]
        raise DataFormatError(path, f"line {line}: expected timestamps increasing strictly, "
                                    f"{timestamps[bad[0] + 1]!r} follows {timestamps[bad[0]]!r}")


def _checked_frames(path: Path, frames: np.ndarray, count: int) -> list[int]:
    array = np.asarray(frames)
    if array.shape != (count,) or array.dtype.kind not in "iu" or count < 2:
        raise DataFormatError(path, f"expected [N >= 2] integer frame numbers, one per pose ({count}), "
                                    f"got shape {array.shape} of {array.dtype}")
    numbers = [int(frame) for frame in array]
    for earlier, later in zip(numbers[:-1], numbers[1:]):
        _check_frame_pair(path, earlier, later)
    return numbers


def _check_frame_pair(path: Path, earlier: int, later: int) -> None:
    if not (0 <= earlier < later):
        raise DataFormatError(path, f"expected frame numbers 0 <= earlier < later, got {earlier} and {later}")


# ----------------------------------------------------------------------------------------- text
def _numbers_text(values) -> str:
    # repr of a Python float is the shortest text that reads back as the same float64
    return " ".join(repr(float(v)) for v in values)


def _number_rows(path: str | Path, columns: int, fields: str, comments: bool) -> tuple[np.ndarray, list[int]]:
    """The numeric lines of ``path`` as ``[N >= 1, columns]`` float64, with their 1-based line numbers."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataFormatError(path, f"file not found (expected lines of {fields})") from None
    except UnicodeDecodeError:
        raise DataFormatError(path, f"not UTF-8 text (expected lines of {fields})") from None
    rows, lines = [], []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or (comments and stripped.startswith("#")):
            continue
        rows.append(_parse_line(path, number, stripped, columns, fields))
        lines.append(number)
    if not rows:
        raise DataFormatError(path, f"no poses: expected lines of {fields}")
    return np.asarray(rows, dtype=np.float64), lines


def _parse_line(path: Path, number: int, line: str, columns: int, fields: str) -> list[float]:
    tokens = line.split()
    try:
        values = [float(token) for token in tokens]
    except ValueError:
        values = None
    if values is None or len(values) != columns:
        raise DataFormatError(path, f"line {number}: expected {columns} numbers ({fields}), found {line!r}")
    if not all(np.isfinite(values)):
        raise DataFormatError(path, f"line {number}: expected finite numbers ({fields}), found {line!r}")
    return values

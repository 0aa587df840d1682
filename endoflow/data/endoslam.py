"""EndoSLAM reader: the synthetic UnityCam layout and the real-camera layouts (HighCam, LowCam, ...).

Converts Unity's left-handed poses and the 8-bit depth maps into the convention of :mod:`endoflow.data.base`,
aligning pose rows logged per physics step to frames by time. See docs/datasets.md, "EndoSLAM".
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from endoflow.config import EndoSLAMConfig
from endoflow.data.base import DatasetReader, Sequence
from endoflow.data.imageio import image_size, read_png8_gray, read_rgb
from endoflow.data.layout import (
    checked_intrinsics,
    checked_size,
    natural_key,
    numbered_files,
    pose_matrices,
    ray_length_to_z_factor,
    report,
    report_frame_gaps,
    shown_numbers,
    sized_loader,
    subfolders,
)
from endoflow.errors import DataFormatError
from endoflow.geometry.camera import scale_intrinsics
from endoflow.geometry.pose import unity_to_opencv

# Third-party UnityCam intrinsics (unconfirmed by the dataset authors) for 320x320 frames.
UNITYCAM_K = np.array([[156.0418, 0.0, 178.5604], [0.0, 155.7529, 181.8043], [0.0, 0.0, 1.0]])
UNITYCAM_SIZE = (320, 320)
UNITYCAM_COLUMNS = ("tX", "tY", "tZ", "rX", "rY", "rZ", "rW", "time(s)")
UNITYCAM_POSE_SUFFIX = "_position_rotation.csv"  # after the organ's file stem: colon, intestine, stomach
CAMERA_COLUMNS = ("ImageFrame", "Pose_Index", "trans_x", "trans_y", "trans_z", "quot_x", "quot_y", "quot_z", "quot_w")
SKIPPED_FOLDERS = ("Calibration",)


class EndoSLAMReader(DatasetReader):
    """Sequences of an EndoSLAM root: ``UnityCam/`` and/or ``Cameras/`` as ``data.endoslam.layout`` says."""

    name = "endoslam"

    def __init__(self, root: str | Path, cfg: EndoSLAMConfig) -> None:
        super().__init__(root)
        self.cfg = cfg

    def sequences(self) -> list[Sequence]:
        unitycam, cameras = self.root / "UnityCam", self.root / "Cameras"
        wanted = {
            "auto": [p for p in (unitycam, cameras) if p.is_dir()],
            "unitycam": [unitycam],
            "camera": [cameras],
        }[self.cfg.layout]
        if not wanted:
            raise DataFormatError(self.root, "no EndoSLAM layout found (expected UnityCam/ or Cameras/)")
        sequences: list[Sequence] = []
        for folder in wanted:
            if not folder.is_dir():
                raise DataFormatError(folder, f"folder not found (data.endoslam.layout is {self.cfg.layout!r})")
            if folder == unitycam:
                sequences += [self._unitycam_sequence(organ) for organ in subfolders(folder, SKIPPED_FOLDERS)]
            else:
                sequences += [self._camera_sequence(trajectory) for trajectory in _camera_trajectories(folder)]
        if not sequences:
            raise DataFormatError(self.root, "no EndoSLAM sequence found under " + ", ".join(p.name for p in wanted))
        return sorted(sequences, key=lambda s: natural_key(s.name))

    # ------------------------------------------------------------------------------------ UnityCam
    def _unitycam_sequence(self, organ: Path) -> Sequence:
        frames = _frames(organ / "Frames", r"image_(\d+)\.png", "image_NNNN.png")
        frame_ids = list(frames)
        size = image_size(frames[frame_ids[0]])
        K = self._unitycam_intrinsics(size)
        name = f"UnityCam/{organ.name}"
        problems: list[str] = []
        report_frame_gaps(problems, organ / "Frames", name, frame_ids)
        depth_paths = _unitycam_depths(organ, frames)
        if depth_paths is None:
            problems.append("no 'Pixelwise Depths' folder: sequence has no depth")
        poses = self._unitycam_poses(_single_file(organ / "Poses", f"*{UNITYCAM_POSE_SUFFIX}"), frame_ids, problems)
        frame_paths = list(frames.values())
        return Sequence(
            dataset=self.name,
            name=name,
            split=self.cfg.split,
            K=K,
            image_size=size,
            frame_ids=frame_ids,
            poses=poses,
            load_rgb=sized_loader(frame_paths, size, read_rgb),
            load_depth=None if depth_paths is None else self._depth_loader(depth_paths, size, K),
            group=organ.name,
            problems=problems,
            source_files=list(zip(frame_paths, depth_paths)) if depth_paths else [(path,) for path in frame_paths],
        )

    def _unitycam_intrinsics(self, size: tuple[int, int]) -> np.ndarray:
        if self.cfg.intrinsics is not None:
            return checked_intrinsics(self.cfg.intrinsics, "data.endoslam.intrinsics")
        height, width = size
        return scale_intrinsics(UNITYCAM_K, width / UNITYCAM_SIZE[1], height / UNITYCAM_SIZE[0])

    def _depth_loader(self, paths: list[Path], size: tuple[int, int], K: np.ndarray):
        scale = np.float32(self.cfg.depth_full_scale_cm / 255.0)
        to_z = ray_length_to_z_factor(K, *size) if self.cfg.depth_is_ray_length else np.float32(1.0)

        def load(i: int) -> np.ndarray:
            depth = checked_size(paths[i], read_png8_gray(paths[i]), size).astype(np.float32) * scale
            return depth * to_z

        return load

    def _unitycam_poses(self, csv: Path, frame_ids: list[int], problems: list[str]) -> np.ndarray:
        rows = read_unitycam_csv(csv)
        valid = np.isfinite(rows).all(axis=1)
        if not valid.all():
            dropped = _data_rows(~valid)
            report(problems, csv, f"dropped {len(dropped)} row(s) with missing values "
                                  f"(empty, not a number, NaN or inf; data row(s) {shown_numbers(dropped)})")
        rows = rows[valid]
        if len(rows) == 0:
            raise DataFormatError(csv, "no pose row with all of " + ",".join(UNITYCAM_COLUMNS))
        _check_quaternions(csv, rows[:, 3:7])
        translations, quaternions = rows[:, :3], rows[:, 3:7]
        if len(rows) != len(frame_ids):
            translations, quaternions = align_by_time(rows[:, 7], translations, quaternions, frame_ids, self.cfg.fps)
            unposed = int(np.isnan(translations[:, 0]).sum())
            report(
                problems,
                csv,
                f"{len(rows)} pose rows for {len(frame_ids)} frames; aligned by time (frame n at "
                f"t0 + (n - n0) / {self.cfg.fps:g} s, interpolated); {unposed} frame(s) after the last logged "
                "time have no pose",
            )
        unity = pose_matrices(translations * self.cfg.unitycam_translation_to_cm, quaternions)
        return unity_to_opencv(unity)

    # ---------------------------------------------------------------------------------- real cameras
    def _camera_sequence(self, trajectory: Path) -> Sequence:
        organ, camera = trajectory.parent, trajectory.parent.parent
        frames = _frames(trajectory / "Frames", r"frame_(\d+)\.jpg", "frame_NNNNNN.jpg")
        frame_ids = list(frames)
        if self.cfg.intrinsics is None:
            raise DataFormatError(
                trajectory,
                "real-camera intrinsics are not in a readable file (calibration ships as MATLAB sessions): "
                "set data.endoslam.intrinsics to the 3x3 pixel K of these frames",
            )
        K = checked_intrinsics(self.cfg.intrinsics, "data.endoslam.intrinsics")
        size = image_size(frames[frame_ids[0]])
        name = f"{camera.name}/{organ.name}/{trajectory.name}"
        problems: list[str] = []
        report_frame_gaps(problems, trajectory / "Frames", name, frame_ids)
        poses = self._camera_poses(_single_file(trajectory / "Poses", "*.xlsx"), frame_ids, problems)
        frame_paths = list(frames.values())
        return Sequence(
            dataset=self.name,
            name=name,
            split=self.cfg.split,
            K=K,
            image_size=size,
            frame_ids=frame_ids,
            poses=poses,
            load_rgb=sized_loader(frame_paths, size, read_rgb),
            load_depth=None,
            group=re.sub(r"-[IVX]+$", "", organ.name),
            problems=problems,
            source_files=[(path,) for path in frame_paths],
        )

    def _camera_poses(self, sheet: Path, frame_ids: list[int], problems: list[str]) -> np.ndarray:
        table = read_camera_sheet(sheet)
        complete = np.isfinite(table.to_numpy(np.float64)).all(axis=1)
        if not complete.all():
            dropped = _data_rows(~complete)
            report(problems, sheet, f"dropped {len(dropped)} row(s) with missing values "
                                    f"(empty, not a number, NaN or inf; data row(s) {shown_numbers(dropped)})")
        table = table[complete]
        duplicated = table["ImageFrame"].duplicated()
        if duplicated.any():
            report(problems, sheet, f"{int(duplicated.sum())} repeated ImageFrame row(s); first kept")
        kept = table[~duplicated]
        rows = kept.set_index(kept["ImageFrame"].astype(np.int64)).reindex(frame_ids)
        _check_quaternions(sheet, rows[["quot_x", "quot_y", "quot_z", "quot_w"]].dropna().to_numpy())
        unposed = int(rows["trans_x"].isna().sum())
        if unposed:
            report(problems, sheet, f"{unposed} of {len(frame_ids)} frames have no pose row")
        translations = rows[["trans_x", "trans_y", "trans_z"]].to_numpy(np.float64) * self.cfg.camera_translation_to_cm
        poses = pose_matrices(translations, rows[["quot_x", "quot_y", "quot_z", "quot_w"]].to_numpy(np.float64))
        return unity_to_opencv(poses) if self.cfg.camera_poses_left_handed else poses


# -------------------------------------------------------------------------------------- file parsing
def read_unitycam_csv(path: Path) -> np.ndarray:
    """UnityCam pose CSV as ``N x 8`` float64 in header order; unparsable values become NaN."""
    try:
        table = pd.read_csv(path, skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        expected = ",".join(UNITYCAM_COLUMNS)
        raise DataFormatError(path, f"unreadable pose CSV ({exc}); expected header {expected}") from None
    table = _with_columns(path, table, UNITYCAM_COLUMNS)
    return table.apply(pd.to_numeric, errors="coerce").to_numpy(np.float64)


def read_camera_sheet(path: Path) -> pd.DataFrame:
    """Real-camera pose sheet (first worksheet) with the documented columns as numbers (NaN if not numeric)."""
    try:
        table = pd.read_excel(path, engine="openpyxl")
    except Exception as exc:  # openpyxl raises many unrelated types for a damaged workbook
        raise DataFormatError(path, f"unreadable pose sheet ({type(exc).__name__}: {exc})") from None
    return _with_columns(path, table, CAMERA_COLUMNS).apply(pd.to_numeric, errors="coerce")


def _with_columns(path: Path, table: pd.DataFrame, columns: tuple[str, ...]) -> pd.DataFrame:
    table = table.rename(columns=lambda c: str(c).strip())
    missing = [c for c in columns if c not in table.columns]
    if missing:
        raise DataFormatError(
            path,
            f"expected columns {', '.join(columns)}; missing {', '.join(missing)} "
            f"(found {', '.join(map(str, table.columns)) or 'none'})",
        )
    return table[list(columns)]


# ------------------------------------------------------------------------------------- pose math
def align_by_time(
    times: np.ndarray, translations: np.ndarray, quaternions: np.ndarray, frame_ids: list[int], fps: float
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at the frame times ``t0 + (n - n0) / fps``: lerp translations, slerp rotations; NaN after the log.

    Returns ``N x 3`` translations and ``N x 4`` quaternions, one row per frame id.
    """
    order = np.argsort(times, kind="stable")
    times, first = np.unique(times[order], return_index=True)  # a repeated time keeps its first row
    translations, quaternions = translations[order][first], quaternions[order][first]
    ids = np.asarray(frame_ids, dtype=np.float64)
    frame_times = times[0] + (ids - ids[0]) / fps
    inside = frame_times <= times[-1] + 1e-9
    out_t = np.full((len(ids), 3), np.nan)
    out_q = np.full((len(ids), 4), np.nan)
    if len(times) == 1:
        out_t[inside], out_q[inside] = translations[0], quaternions[0]
        return out_t, out_q
    left = np.clip(np.searchsorted(times, frame_times[inside], side="right") - 1, 0, len(times) - 2)
    weight = np.clip((frame_times[inside] - times[left]) / (times[left + 1] - times[left]), 0.0, 1.0)
    out_t[inside] = translations[left] + weight[:, None] * (translations[left + 1] - translations[left])
    out_q[inside] = slerp_xyzw(quaternions[left], quaternions[left + 1], weight)
    return out_t, out_q


def slerp_xyzw(q0: np.ndarray, q1: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Spherical interpolation ``[N, 4]`` between unit quaternions along the shorter arc (``q ~ -q``)."""
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    angle = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))
    sin_angle = np.sin(angle)
    tiny = sin_angle < 1e-9
    safe = np.where(tiny, 1.0, sin_angle)
    a = np.where(tiny, 1 - weight, np.sin((1 - weight) * angle) / safe)
    b = np.where(tiny, weight, np.sin(weight * angle) / safe)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _check_quaternions(path: Path, quaternions: np.ndarray) -> None:
    zero = int((np.linalg.norm(quaternions, axis=1) == 0).sum())
    if zero:
        raise DataFormatError(path, f"{zero} pose row(s) with a zero quaternion (all four components 0)")


# ------------------------------------------------------------------------------------------ layout
def _camera_trajectories(cameras: Path) -> list[Path]:
    return [
        trajectory
        for camera in subfolders(cameras, SKIPPED_FOLDERS)
        for organ in subfolders(camera, SKIPPED_FOLDERS)
        for trajectory in subfolders(organ, SKIPPED_FOLDERS)
    ]


def _frames(folder: Path, pattern: str, described: str) -> dict[int, Path]:
    if not folder.is_dir():
        raise DataFormatError(folder, f"frame folder not found (expected {described} files here)")
    frames = numbered_files(folder, pattern)
    if not frames:
        raise DataFormatError(folder, f"empty sequence: no {described} frames")
    return frames


def _unitycam_depths(organ: Path, frames: dict[int, Path]) -> list[Path] | None:
    folder = organ / "Pixelwise Depths"
    if not folder.is_dir():
        return None
    depths = numbered_files(folder, r"aov_image_(\d+)\.png")
    for number, frame in frames.items():
        if number not in depths:
            raise DataFormatError(folder / f"aov_{frame.name}", f"missing image: depth map for {frame.name} not found")
    return [depths[number] for number in frames]


def _single_file(folder: Path, pattern: str) -> Path:
    matches = sorted(folder.glob(pattern)) if folder.is_dir() else []
    if len(matches) != 1:
        found = ", ".join(p.name for p in matches) or "none"
        raise DataFormatError(folder, f"expected exactly one pose file {pattern}, found {found}")
    return matches[0]


def _data_rows(mask: np.ndarray) -> list[int]:
    """1-based data-row numbers (the header not counted) where ``mask`` is true."""
    return [int(i) + 1 for i in np.flatnonzero(mask)]

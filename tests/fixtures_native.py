"""Tiny datasets written in each native layout, byte-format faithful, with what a reader must return.

Each ``write_*`` function creates one dataset layout under ``root`` and returns, per sequence, a
:class:`NativeSequence` holding the values a correct reader yields (RGB as written, z-depth in cm, OpenCV
camera-to-world poses in cm, K for the stored size). Formats follow ``docs/datasets.md``:

- SimCol3D: 16-bit RGBA FrameBuffer PNGs (8-bit values times 256, alpha 65280), 16-bit depth PNGs on the
  ``/255/256*20`` cm scale, the real ``cam.txt`` bytes (one line, no newline), Unity left-handed
  ``SavedPosition``/``SavedRotationQuaternion`` files with quaternion sign flips.
- EndoSLAM UnityCam: 8-bit PNG frames, 8-bit RGBA depth with equal channels, a pose CSV with the real header;
  optionally with fewer rows than frames, logged at other times, and a NaN last row (as seen in the data).
- EndoSLAM real camera: JPEG frames and an ``.xlsx`` pose sheet (metres) with one frame left without a row.
- SceneNet: 16-bit depth in mm of ray length on known planes, JPEG photos, frame numbers 0, 25, 50, 100.

Expected values are computed here from first principles (explicit formulas), not through the readers.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import pandas as pd

from endoflow.config import Params
from endoflow.data.imageio import write_png

SIMCOL_CAM_TXT = "227.60416 0 227.60416 0 237.5 237.5 0 0 1"
SIMCOL_K_475 = np.array([[227.60416, 0.0, 227.60416], [0.0, 237.5, 237.5], [0.0, 0.0, 1.0]])
UNITYCAM_K_320 = np.array([[156.0418, 0.0, 178.5604], [0.0, 155.7529, 181.8043], [0.0, 0.0, 1.0]])
FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])


@dataclass
class NativeSequence:
    """What a reader must return for one written sequence (``rgb`` from JPEG is only approximate)."""

    name: str
    split: str
    group: str
    frame_ids: list[int]
    K: Optional[np.ndarray]
    rgb: Optional[list[np.ndarray]]
    depth_cm: Optional[list[np.ndarray]]
    T_world_cam: Optional[np.ndarray]  # N x 4 x 4, NaN-filled where a frame has no pose


# --------------------------------------------------------------------------------------- geometry
def rotation(axis: tuple[float, float, float], angle: float) -> np.ndarray:
    """3x3 right-handed rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix whose angle is below pi (w > 0)."""
    w = np.sqrt(max(1.0 + np.trace(R), 0.0)) / 2
    return np.array([(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w])


def pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def scaled_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K after resizing by (sx, sy) with pixel centres at integers: ``c' = (c + 0.5) s - 0.5``."""
    return np.array(
        [[K[0, 0] * sx, 0.0, (K[0, 2] + 0.5) * sx - 0.5], [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5], [0, 0, 1.0]]
    )


def _random_rgb(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    return rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)


def _smooth_rgb(height: int, width: int, index: int) -> np.ndarray:
    """Smooth colours (JPEG keeps them within a few levels)."""
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([60 + 4 * u, 50 + 5 * v, np.full_like(u, 40 + 20 * index)], axis=-1).astype(np.uint8)


def _write_jpeg(path: Path, rgb: np.ndarray) -> None:
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 98])
    assert ok
    path.write_bytes(data.tobytes())


# --------------------------------------------------------------------------------------- SimCol3D
def simcol_trajectory(frames: int, offset: float = 0.0) -> np.ndarray:
    """OpenCV camera-to-world poses (cm): forward along a turning path with some roll."""
    poses = []
    for i in range(frames):
        R = rotation((0.2, 1.0, 0.1), 0.4 + 0.07 * i + offset) @ rotation((0.0, 0.0, 1.0), 0.03 * i)
        t = np.array([-30.5 + 0.13 * i, 16.3 - 0.02 * i + offset, -3.4 + 0.2 * i])
        poses.append(pose(R, t))
    return np.stack(poses)


def write_simcol(
    root: Path,
    scenes: Optional[dict[str, tuple[str, ...]]] = None,
    frames: int = 3,
    size: int = 32,
    seed: int = 0,
    split_of: Optional[dict[str, str]] = None,
) -> dict[str, NativeSequence]:
    """SimCol3D layout (default: ``SyntheticColon_I`` with S1 and S4, ``SyntheticColon_III`` with O1).

    ``split_of`` maps sequence names to the split the default config gives them (train otherwise).
    """
    scenes = scenes or {"SyntheticColon_I": ("S1", "S4"), "SyntheticColon_III": ("O1",)}
    split_of = split_of or {"S4": "val", "O1": "test"}
    rng = np.random.default_rng(seed)
    expected = {}
    for scene_index, (scene, names) in enumerate(scenes.items()):
        scene_dir = root / scene
        scene_dir.mkdir(parents=True, exist_ok=True)
        (scene_dir / "cam.txt").write_text(SIMCOL_CAM_TXT)
        for sequence_index, name in enumerate(names):
            expected[name] = _write_simcol_sequence(
                scene_dir, name, frames, size, rng, offset=0.1 * (3 * scene_index + sequence_index)
            )
            expected[name].split = split_of.get(name, "train")
    return expected


def _write_simcol_sequence(
    scene_dir: Path, name: str, frames: int, size: int, rng: np.random.Generator, offset: float
) -> NativeSequence:
    folder = scene_dir / f"Frames_{name}"
    folder.mkdir()
    rgbs, depths = [], []
    for i in range(frames):
        rgb = _random_rgb(rng, size, size)
        rgba16 = np.concatenate([rgb, np.full((size, size, 1), 255, np.uint8)], axis=-1).astype(np.uint16) * 256
        write_png(folder / f"FrameBuffer_{i:04d}.png", rgba16)
        levels = rng.integers(1, 256, size=(size, size)).astype(np.uint16)
        write_png(folder / f"Depth_{i:04d}.png", levels * 256)
        rgbs.append(rgb)
        depths.append(levels.astype(np.float64) / 255 * 20)
    T_world_cam = simcol_trajectory(frames, offset)
    unity = FLIP_Y @ T_world_cam @ FLIP_Y
    quaternions = np.stack([quaternion_xyzw(M[:3, :3]) for M in unity])
    quaternions[1::2] *= -1  # the data has sign flips; q and -q are the same rotation
    _write_rows(scene_dir / f"SavedPosition_{name}.txt", unity[:, :3, 3])
    _write_rows(scene_dir / f"SavedRotationQuaternion_{name}.txt", quaternions)
    return NativeSequence(
        name=name,
        split="train",
        group=scene_dir.name,
        frame_ids=list(range(frames)),
        K=scaled_K(SIMCOL_K_475, size / 475, size / 475),
        rgb=rgbs,
        depth_cm=depths,
        T_world_cam=T_world_cam,
    )


def _write_rows(path: Path, rows: np.ndarray) -> None:
    path.write_text("".join(" ".join(repr(float(v)) for v in row) + "\n" for row in rows))


# ------------------------------------------------------------------------------- EndoSLAM UnityCam
def unitycam_pose_at(time: float) -> np.ndarray:
    """Unity (left-handed) camera-to-world at ``time`` s: constant velocity and constant angular velocity,
    so linear and spherical interpolation between logged samples are exact."""
    R = rotation((0.3, 0.9, -0.2), 0.2) @ rotation((0.1, 0.2, 1.0), 0.8 * time)
    t = np.array([1.0, 2.0, -3.0]) + np.array([0.5, -0.25, 1.5]) * time
    return pose(R, t)


def write_endoslam_unitycam(
    root: Path,
    organ: str = "Colon",
    frames: int = 8,
    size: int = 32,
    matched: bool = True,
    depth_full_scale_cm: float = 20.0,
    fps: float = 30.0,
    seed: int = 0,
) -> NativeSequence:
    """``UnityCam/<organ>/{Frames, Pixelwise Depths, Poses}``.

    ``matched``: one pose row per frame at the frame times. Otherwise the log starts at the first frame
    but is sampled every 0.8 frame intervals for 7 rows (so it ends at frame time 4.8), followed by a NaN
    row: frames 0..4 get interpolated poses, later frames none.
    """
    rng = np.random.default_rng(seed)
    organ_dir = root / "UnityCam" / organ
    for sub in ("Frames", "Pixelwise Depths", "Poses"):
        (organ_dir / sub).mkdir(parents=True, exist_ok=True)
    rgbs, depths = [], []
    for i in range(frames):
        rgb = _random_rgb(rng, size, size)
        write_png(organ_dir / "Frames" / f"image_{i:04d}.png", rgb)
        level = rng.integers(0, 256, size=(size, size), dtype=np.uint8)
        rgba = np.stack([level, level, level, np.full_like(level, 255)], axis=-1)
        write_png(organ_dir / "Pixelwise Depths" / f"aov_image_{i:04d}.png", rgba)
        rgbs.append(rgb)
        depths.append(level.astype(np.float64) / 255 * depth_full_scale_cm)
    t0 = 2.5
    frame_times = t0 + np.arange(frames) / fps
    log_times = frame_times if matched else t0 + 0.8 * np.arange(7) / fps
    rows = [_unity_row(unitycam_pose_at(t), t) for t in log_times]
    if not matched:
        rows.append(["NaN"] * 8)
    csv = organ_dir / "Poses" / f"{organ.split()[-1].lower()}_position_rotation.csv"
    csv.write_text("tX,tY,tZ,rX,rY,rZ,rW,time(s)\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    T_world_cam = np.stack([FLIP_Y @ unitycam_pose_at(t) @ FLIP_Y for t in frame_times])
    if not matched:
        T_world_cam[frame_times > log_times[-1] + 1e-9] = np.nan
    return NativeSequence(
        name=f"UnityCam/{organ}",
        split="test",
        group=organ,
        frame_ids=list(range(frames)),
        K=scaled_K(UNITYCAM_K_320, size / 320, size / 320),
        rgb=rgbs,
        depth_cm=depths,
        T_world_cam=T_world_cam,
    )


def _unity_row(M: np.ndarray, time: float) -> list:
    return [repr(float(v)) for v in (*M[:3, 3], *quaternion_xyzw(M[:3, :3]))] + [repr(float(time))]


# --------------------------------------------------------------------------- EndoSLAM real cameras
CAMERA_COLUMNS = ["ImageFrame", "Pose_Index", "trans_x", "trans_y", "trans_z", "quot_x", "quot_y", "quot_z", "quot_w"]


def write_endoslam_camera(
    root: Path,
    camera: str = "HighCam",
    organ: str = "Colon-IV",
    trajectory: str = "TumorfreeTrajectory_1",
    frames: int = 4,
    size: tuple[int, int] = (24, 32),
    columns: Optional[list[str]] = None,
) -> NativeSequence:
    """``Cameras/<camera>/<organ>/<trajectory>/{Frames/frame_%06d.jpg, Poses/poses.xlsx}`` (metres).

    The sheet lists frames in reverse order (the join is on ``ImageFrame``) and has no row for the last
    frame. ``columns`` renames the sheet's columns (to write a malformed sheet).
    """
    height, width = size
    folder = root / "Cameras" / camera / organ / trajectory
    (folder / "Frames").mkdir(parents=True)
    (folder / "Poses").mkdir()
    rgbs = []
    for i in range(frames):
        rgb = _smooth_rgb(height, width, i)
        _write_jpeg(folder / "Frames" / f"frame_{i:06d}.jpg", rgb)
        rgbs.append(rgb)
    T_world_cam = np.full((frames, 4, 4), np.nan)
    rows = []
    for i in reversed(range(frames - 1)):
        R, t_m = rotation((1.0, 0.5, 0.2), 0.1 * i), np.array([0.01 * i, -0.02, 0.03 * i])
        T_world_cam[i] = pose(R, t_m * 100)
        rows.append([i, 100 + i, *t_m, *quaternion_xyzw(R)])
    table = pd.DataFrame(rows, columns=columns or CAMERA_COLUMNS)
    table.to_excel(folder / "Poses" / "poses.xlsx", index=False, engine="openpyxl")
    return NativeSequence(
        name=f"{camera}/{organ}/{trajectory}",
        split="test",
        group=organ.split("-")[0],
        frame_ids=list(range(frames)),
        K=None,
        rgb=rgbs,
        depth_cm=None,
        T_world_cam=T_world_cam,
    )


# ---------------------------------------------------------------------------------------- SceneNet
def scenenet_K(height: int, width: int) -> np.ndarray:
    """The documented 60 x 45 degree camera, centre at ``W/2, H/2`` with SceneNet's +0.5 pixel centres."""
    fx, fy = (width / 2) / np.tan(np.radians(30)), (height / 2) / np.tan(np.radians(22.5))
    return np.array([[fx, 0, width / 2 - 0.5], [0, fy, height / 2 - 0.5], [0, 0, 1.0]])


def scenenet_ray_norm(height: int, width: int) -> np.ndarray:
    """``|((u + 0.5 - W/2) / fx, (v + 0.5 - H/2) / fy, 1)|`` per pixel, as datasets.md states it."""
    K = scenenet_K(height, width)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x = (u + 0.5 - width / 2) / K[0, 0]
    y = (v + 0.5 - height / 2) / K[1, 1]
    return np.sqrt(x * x + y * y + 1)


def write_scenenet(
    root: Path,
    split: str = "train",
    part: str = "0",
    trajectory: str = "7",
    frame_ids: tuple[int, ...] = (0, 25, 50, 100),
    size: tuple[int, int] = (24, 32),
    photos: bool = True,
) -> NativeSequence:
    """``<split>/<part>/<trajectory>/{depth/<n>.png, photo/<n>.jpg}``: frame k sees a fronto-parallel plane
    at ``z = 150 + 40 k`` cm (ray length in mm, rounded), with no reading in the top-left pixel."""
    height, width = size
    folder = root / split / part / trajectory
    (folder / "depth").mkdir(parents=True)
    if photos:
        (folder / "photo").mkdir()
    norm = scenenet_ray_norm(height, width)
    depths, rgbs = [], []
    for k, n in enumerate(frame_ids):
        ray_mm = np.round((150.0 + 40.0 * k) * 10 * norm).astype(np.uint16)
        ray_mm[0, 0] = 0
        write_png(folder / "depth" / f"{n}.png", ray_mm)
        depths.append(ray_mm.astype(np.float64) / 10 / norm)
        if photos:
            rgbs.append(_smooth_rgb(height, width, k))
            _write_jpeg(folder / "photo" / f"{n}.jpg", rgbs[-1])
    return NativeSequence(
        name=f"{split}/{part}/{trajectory}",
        split=split,
        group=part,
        frame_ids=list(frame_ids),
        K=scenenet_K(height, width),
        rgb=rgbs if photos else None,
        depth_cm=depths,
        T_world_cam=None,
    )


# ------------------------------------------------------------------------------- damaging a copy
def replace_line(path: Path, index: int, text: str) -> None:
    """Line ``index`` (0-based) of a text file replaced by ``text``, as a damaged export would have it."""
    lines = path.read_text().splitlines()
    lines[index] = text
    path.write_text("\n".join(lines) + "\n")


def remove_simcol_frame(scene_dir: Path, name: str, number: int) -> None:
    """Delete frame ``number`` (FrameBuffer and Depth) of sequence ``name``, leaving the pose files whole."""
    folder = scene_dir / f"Frames_{name}"
    (folder / f"FrameBuffer_{number:04d}.png").unlink()
    (folder / f"Depth_{number:04d}.png").unlink()


def repaint_simcol_frame(scene_dir: Path, name: str, number: int, seed: int = 99) -> None:
    """New random pixels for FrameBuffer ``number`` of ``name``, with an mtime one second later than before."""
    path = scene_dir / f"Frames_{name}" / f"FrameBuffer_{number:04d}.png"
    before = path.stat()
    height, width = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).shape[:2]
    rgb = _random_rgb(np.random.default_rng(seed), height, width)
    rgba16 = np.concatenate([rgb, np.full((height, width, 1), 255, np.uint8)], axis=-1).astype(np.uint16) * 256
    write_png(path, rgba16)
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns + 1_000_000_000))


# ------------------------------------------------------------------------------ preprocessing
def preprocess_params(dataset: str, root: Path, size: int = 16, samples_per_shard: int = 2) -> Params:
    """Params reading ``dataset`` from ``root`` into small shards: one process, no shard multiple."""
    params = Params()
    getattr(params.data, dataset).root = str(root)
    params.data.size = size
    params.preprocess = params.preprocess.replace(workers=1, samples_per_shard=samples_per_shard, shard_multiple=1)
    return params

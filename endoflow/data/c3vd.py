"""C3VD reader (Bobrow et al., MedIA 2023: a real colonoscope in silicone phantoms, depth and poses registered):
the native layout, its fisheye frames and depth undistorted to a pinhole, in the common convention of
:mod:`endoflow.data.base`.

A sequence is a folder holding ``<n>_color.png`` (8-bit RGB, ``n`` not zero-padded), ``<nnnn>_depth.tiff``
(16-bit, 0..65535 for 0..100 mm of z-depth, 0 unknown) and ``pose.txt`` (one line per frame of the sequence: the 16
numbers of a camera-to-world 4x4, column by column, translation in mm). The camera is Scaramuzza's omnidirectional
model as MATLAB's fisheye calibration writes it (centre counted from pixel 1, which we move to our 0-based pixels),
in ``data.c3vd.calibration``: a pixel's offset from ``(cx, cy)``, taken through the affine
``[[e, f], [g, 1]]``, is ``(x, y)`` at ``rho = |(x, y)|``, and its ray is ``(x, y, a0 + a2 rho^2 + a3 rho^3 +
a4 rho^4)``. Frames and depth are resampled onto a pinhole with the same centre, axis and size, focal
``data.c3vd.focal_px`` (the calibration's ``a0`` by default: the fisheye's own focal at its centre), colour bilinearly
and depth by nearest neighbour (the centre and the axis are the same, so z-depth stays z-depth). See
docs/datasets.md, "C3VD".
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from endoflow.config import C3VDConfig
from endoflow.data.base import DatasetReader, Sequence
from endoflow.data.imageio import image_size, read_gray16, read_rgb
from endoflow.data.layout import (natural_key, numbered_files, report_frame_gaps, report_non_finite_rows, shown_numbers,
                                  sized_loader)
from endoflow.errors import DataFormatError
from endoflow.geometry.pose import nearest_rotation, orthonormality_error

COLOR_PATTERN = r"(\d+)_color\.png"
DEPTH_PATTERN = r"(\d+)_depth\.tiff"
POSE_FILE = "pose.txt"
DEPTH_FULL_SCALE_CM = 10.0  # 65535 counts are 100 mm
MM_PER_CM = 10.0
# R^T R off the identity by more than this in any element is a damaged pose, not the rounding of pose.txt's six
# significant digits (up to 1.5e-6 there)
ROTATION_TOLERANCE = 1e-4
CALIBRATION_FIELDS = ("width", "height", "cx", "cy", "a0", "a2", "a3", "a4", "e", "f", "g")


@dataclass(frozen=True)
class OmnidirectionalCamera:
    """Scaramuzza's model as C3VD's calibration gives it (module docstring); sizes and centre in pixels."""

    width: int
    height: int
    cx: float
    cy: float
    a0: float
    a2: float
    a3: float
    a4: float
    e: float
    f: float
    g: float

    def polynomial(self, rho: np.ndarray) -> np.ndarray:
        return self.a0 + self.a2 * rho**2 + self.a3 * rho**3 + self.a4 * rho**4

    def project(self, rays: np.ndarray) -> np.ndarray:
        """Pixels ``[..., 2]`` (u, v) of camera rays ``[..., 3]`` in front of the camera (z > 0)."""
        radial = np.linalg.norm(rays[..., :2], axis=-1)
        rho = self._rho_of_slope(rays[..., 2] / np.maximum(radial, 1e-12))
        sensor = rays[..., :2] * (rho / np.maximum(radial, 1e-12))[..., None]
        u = self.e * sensor[..., 0] + self.f * sensor[..., 1] + self.cx
        v = self.g * sensor[..., 0] + sensor[..., 1] + self.cy
        return np.stack([u, v], axis=-1)

    def _rho_of_slope(self, slope: np.ndarray) -> np.ndarray:
        """``rho`` with ``polynomial(rho) / rho == slope`` (z over the radial distance of a ray), by interpolation in
        a table over the image's radius: the ratio falls monotonically there."""
        rho = np.linspace(1e-3, float(np.hypot(self.width, self.height)), 20001)
        ratio = self.polynomial(rho) / rho
        if np.any(np.diff(ratio) >= 0):
            raise ValueError("calibration: polynomial(rho) / rho must fall over the image for rays to be unique")
        return np.interp(slope, ratio[::-1], rho[::-1])


def read_calibration(path: Path) -> OmnidirectionalCamera:
    """C3VD's ``*_omnidirectional_values.txt``: the 11 numbers of :data:`CALIBRATION_FIELDS`, in that order."""
    if not path.is_file():
        raise DataFormatError(path, "C3VD calibration not found (set data.c3vd.calibration)")
    try:
        numbers = [float(word) for word in path.read_text().split()]
    except ValueError:
        raise DataFormatError(path, f"expected {len(CALIBRATION_FIELDS)} numbers: "
                                    f"{' '.join(CALIBRATION_FIELDS)}") from None
    if len(numbers) != len(CALIBRATION_FIELDS) or not np.all(np.isfinite(numbers)):
        raise DataFormatError(path, f"expected {len(CALIBRATION_FIELDS)} finite numbers ({' '.join(CALIBRATION_FIELDS)}), "
                                    f"found {len(numbers)}")
    values = dict(zip(CALIBRATION_FIELDS, numbers))
    # MATLAB's fisheye calibration (positive a0, the stretch matrix [[e, f], [g, 1]]) counts pixels from 1
    values["cx"] -= 1
    values["cy"] -= 1
    return OmnidirectionalCamera(width=int(values.pop("width")), height=int(values.pop("height")), **values)


def pinhole(camera: OmnidirectionalCamera, focal_px: float | None) -> np.ndarray:
    """K of the pinhole the frames are resampled onto: the fisheye's centre, ``focal_px`` (None: ``a0``)."""
    focal = camera.a0 if focal_px is None else focal_px
    return np.array([[focal, 0.0, camera.cx], [0.0, focal, camera.cy], [0.0, 0.0, 1.0]])


@lru_cache(maxsize=4)
def undistortion_maps(camera: OmnidirectionalCamera, focal_px: float | None) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps: for each pinhole pixel, where its ray meets the fisheye image."""
    K = pinhole(camera, focal_px)
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    pixels = camera.project(rays)
    return pixels[..., 0].astype(np.float32), pixels[..., 1].astype(np.float32)


class C3VDReader(DatasetReader):
    """Sequences of a C3VD root: each folder below it that holds ``pose.txt`` and colour frames."""

    name = "c3vd"

    def __init__(self, root: str | Path, cfg: C3VDConfig) -> None:
        super().__init__(root)
        self.cfg = cfg

    def sequences(self) -> list[Sequence]:
        folders = sorted((p.parent for p in self.root.glob(f"*/{POSE_FILE}")), key=lambda p: natural_key(p.name))
        if not folders:
            raise DataFormatError(self.root, f"no C3VD sequence found: expected folders holding {POSE_FILE} and "
                                             f"<n>_color.png frames")
        camera = read_calibration(self.root / self.cfg.calibration)
        return [self._read_sequence(folder, camera) for folder in folders]

    def _read_sequence(self, folder: Path, camera: OmnidirectionalCamera) -> Sequence:
        colours = numbered_files(folder, COLOR_PATTERN)
        if not colours:
            raise DataFormatError(folder, "no <n>_color.png frames")
        frame_ids = sorted(colours)
        depths = numbered_files(folder, DEPTH_PATTERN)
        missing = [i for i in frame_ids if i not in depths]
        if missing:
            raise DataFormatError(folder, f"no depth for frames {missing[:5]}: expected {missing[0]:04d}_depth.tiff")
        size = image_size(colours[frame_ids[0]])
        if size != (camera.height, camera.width):
            raise DataFormatError(colours[frame_ids[0]], f"frames are {size[1]}x{size[0]}, the calibration "
                                                         f"describes {camera.width}x{camera.height}")
        problems: list[str] = []
        report_frame_gaps(problems, folder, folder.name, frame_ids)
        poses = read_poses(folder / POSE_FILE, frame_ids, problems)
        maps = undistortion_maps(camera, self.cfg.focal_px)
        colour_paths = [colours[i] for i in frame_ids]
        depth_paths = [depths[i] for i in frame_ids]
        return Sequence(
            dataset=self.name, name=folder.name, split=self._split(folder.name), K=pinhole(camera, self.cfg.focal_px),
            image_size=size, frame_ids=frame_ids, poses=poses,
            load_rgb=undistorting(sized_loader(colour_paths, size, read_rgb), maps, cv2.INTER_LINEAR),
            load_depth=undistorting(sized_loader(depth_paths, size, decode_depth), maps, cv2.INTER_NEAREST),
            group=folder.name.split("_")[0], problems=problems, source_files=list(zip(colour_paths, depth_paths)))

    def _split(self, name: str) -> str:
        if name in self.cfg.test:
            return "test"
        if name in self.cfg.val:
            return "val"
        return "train"


def undistorting(load: Callable[[int], np.ndarray], maps: tuple[np.ndarray, np.ndarray], interpolation: int
                 ) -> Callable[[int], np.ndarray]:
    """``i -> load(i)`` undistorted (:func:`undistorted`): the native frame's size is checked before it is
    resampled, which gives every frame the calibration's size."""
    return lambda i: undistorted(load(i), maps, interpolation)


def undistorted(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray], interpolation: int) -> np.ndarray:
    """``image`` resampled onto the pinhole; what the fisheye does not see is 0 (unknown depth, black)."""
    return cv2.remap(image, maps[0], maps[1], interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def decode_depth(path: Path) -> np.ndarray:
    """C3VD depth TIFF -> ``H x W`` float32 z-depth in cm (0..65535 for 0..10 cm; 0 unknown)."""
    return read_gray16(path).astype(np.float32) * np.float32(DEPTH_FULL_SCALE_CM / 65535.0)


def read_poses(path: Path, frame_ids: list[int], problems: list[str]) -> np.ndarray:
    """``T_world_cam`` (cm) of ``frame_ids`` from ``pose.txt``: line ``n`` is frame ``n``, 16 comma-separated numbers
    of the 4x4 written column by column, translation in mm."""
    if not path.is_file():
        raise DataFormatError(path, "pose file not found")
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(word) for word in line.split(",")]
        except ValueError:
            raise DataFormatError(path, f"line {number}: expected 16 comma-separated numbers") from None
        if len(values) != 16:
            raise DataFormatError(path, f"line {number}: expected 16 comma-separated numbers, found {len(values)}")
        rows.append(values)
    if len(rows) <= frame_ids[-1]:
        raise DataFormatError(path, f"{len(rows)} poses for frame numbers up to {frame_ids[-1]} (line n is frame n)")
    poses = np.asarray(rows, dtype=np.float64)[frame_ids].reshape(-1, 4, 4).transpose(0, 2, 1)
    report_non_finite_rows(problems, path, poses.reshape(len(frame_ids), -1), frame_ids)
    bottom = poses[:, 3]
    if not np.allclose(bottom[np.isfinite(bottom).all(axis=1)], [0, 0, 0, 1], atol=1e-6):
        raise DataFormatError(path, "a pose's last row is not 0 0 0 1: the file is not column-major 4x4 transforms")
    poses[:, :3, :3] = _rotations_made_exact(path, poses[:, :3, :3], frame_ids)
    poses[:, :3, 3] /= MM_PER_CM
    return poses


def _rotations_made_exact(path: Path, rotations: np.ndarray, frame_ids: list[int]) -> np.ndarray:
    """Each finite rotation of ``pose.txt`` projected onto the nearest rotation, or an error naming the frames
    whose matrix is no rotation (frames without a pose are left as they are). The file's six significant digits
    leave its rotations orthonormal only to about 1.5e-6, and the relative rotations composed from them further
    off: trajectory tools refuse those (``evo`` checks to 1e-6)."""
    finite = np.flatnonzero(np.isfinite(rotations).all(axis=(1, 2)))
    known = rotations[finite]
    gram_error = orthonormality_error(known)
    stretched, mirrored = gram_error > ROTATION_TOLERANCE, np.linalg.det(known) < 0
    problems = []
    if stretched.any():
        problems.append(f"frame(s) {shown_numbers([frame_ids[i] for i in finite[stretched]])}: R^T R differs from "
                        f"the identity by up to {gram_error[stretched].max():.2g} (at most {ROTATION_TOLERANCE:g} "
                        f"expected)")
    if mirrored.any():
        problems.append(f"frame(s) {shown_numbers([frame_ids[i] for i in finite[mirrored]])}: determinant "
                        f"negative (a mirror)")
    if problems:
        raise DataFormatError(path, "the 3x3 block is not a rotation: " + "; ".join(problems))
    exact = rotations.copy()
    for i in finite:
        exact[i] = nearest_rotation(rotations[i])
    return exact

"""Pinhole intrinsics a user gives for frames: read from a file or four numbers, and checked against the frames.

Accepted forms, always in pixels of the frames' native size: a SimCol3D ``cam.txt`` (``.txt``), a YAML or JSON file
with ``fx, fy, cx, cy`` and the ``width, height`` they belong to, or the text ``"fx,fy,cx,cy"``. ``endoflow
reconstruct --intrinsics`` and the video dataset (``data.video.intrinsics`` and a sequence's sidecar file) read them
here.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import numpy as np
import yaml

from endoflow.data.crop import Crop, frame_region, model_view
from endoflow.data.simcol import parse_cam_txt
from endoflow.errors import DataFormatError

# Plausible field of view of a frame, each axis, degrees: a pinhole camera's is below 180 and endoscopes reach about
# 170; focal lengths outside (fx = 1 px, or 1e9 px) are in other units or of another image size.
FIELD_OF_VIEW_DEG = (10.0, 170.0)


def read_intrinsics(spec: str, native_size: tuple[int, int]) -> np.ndarray:
    """``3 x 3`` K from ``spec``, a file or ``"fx,fy,cx,cy"`` (module docstring), for frames of ``native_size``
    ``(height, width)``. Not yet checked: see :func:`check_intrinsics`."""
    if Path(spec).is_file():
        return _intrinsics_file(Path(spec), native_size)
    return _intrinsics_numbers(spec)


def _intrinsics_numbers(spec: str) -> np.ndarray:
    try:
        fx, fy, cx, cy = (float(v) for v in spec.split(","))
    except ValueError:
        raise DataFormatError(spec, "expected an intrinsics file or four numbers fx,fy,cx,cy (pixels)") from None
    return pinhole(fx, fy, cx, cy)


def _intrinsics_file(path: Path, native_size: tuple[int, int]) -> np.ndarray:
    if path.suffix.lower() == ".txt":
        return parse_cam_txt(path.read_text(), path)
    try:
        raw = json.loads(path.read_text()) if path.suffix.lower() == ".json" else yaml.safe_load(path.read_text())
        fx, fy, cx, cy = (float(raw[k]) for k in ("fx", "fy", "cx", "cy"))
        width, height = int(raw["width"]), int(raw["height"])
    except (ValueError, TypeError, KeyError, yaml.YAMLError) as exc:
        raise DataFormatError(path, f"expected fx, fy, cx, cy (pixels) and the width and height they belong to "
                                    f"({type(exc).__name__}: {exc})") from None
    if (height, width) != tuple(native_size):
        raise DataFormatError(path, f"intrinsics for {width}x{height} px, but the frames are "
                                    f"{native_size[1]}x{native_size[0]}: give intrinsics for the frames' size")
    return pinhole(fx, fy, cx, cy)


def pinhole(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The ``3 x 3`` K of focal lengths ``fx, fy`` and principal point ``cx, cy`` (pixels)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def assumed_intrinsics(size: tuple[int, int], diagonal_fov_deg: float) -> np.ndarray:
    """The K of a pinhole with square pixels, its principal point at the centre of ``size`` ``(height, width)``
    frames and a field of view of ``diagonal_fov_deg`` across their diagonal: what is assumed of a camera nobody
    calibrated (endoscopes see about 140 degrees across)."""
    height, width = size
    focal = math.hypot(width, height) / 2 / math.tan(math.radians(diagonal_fov_deg) / 2)
    return pinhole(focal, focal, (width - 1) / 2, (height - 1) / 2)


def check_intrinsics(K: np.ndarray, native_size: tuple[int, int], source: str, crop: Optional[Crop] = None) -> None:
    """Refuse, naming ``source``, a K that cannot be the frames' (non-finite, a focal length <= 0, the principal
    point outside the image), whose field of view is implausible (:data:`FIELD_OF_VIEW_DEG`: focal lengths in
    other units or of another image size), or whose principal point lies outside the square the model sees."""
    height, width = native_size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (np.isfinite(K).all() and fx > 0 and fy > 0 and 0 < cx < width and 0 < cy < height):
        raise DataFormatError(source, f"intrinsics fx={fx:g}, fy={fy:g}, cx={cx:g}, cy={cy:g} do not fit "
                                      f"{width}x{height} px frames (focal lengths > 0, principal point inside the "
                                      f"image)")
    across = [math.degrees(2 * math.atan(extent / (2 * focal))) for extent, focal in ((width, fx), (height, fy))]
    low, high = FIELD_OF_VIEW_DEG
    if not all(low <= angle <= high for angle in across):
        raise DataFormatError(source, f"intrinsics fx={fx:g}, fy={fy:g} give the {width}x{height} px frames a field "
                                      f"of view of {across[0]:.3g} x {across[1]:.3g} degrees, outside the plausible "
                                      f"{low:g} to {high:g}: give focal lengths in pixels of these frames")
    view = model_view(frame_region(native_size, crop, source))
    if not (view.x - 0.5 <= cx <= view.x + view.width - 0.5 and view.y - 0.5 <= cy <= view.y + view.height - 0.5):
        raise DataFormatError(source, f"principal point cx={cx:g}, cy={cy:g} lies outside the square the model sees, "
                                      f"{view} (the centre square of the {'--crop region' if crop else 'frames'}): "
                                      f"these intrinsics are not of these frames, or --crop cuts the optical axis "
                                      f"away")

"""Frame encoding: a native frame as the model's square image, its K and its depth as 16-bit counts.

Every frame a model sees goes through this one crop and resize: preprocessing stores training frames with it
(:mod:`endoflow.data.shard_writer`) and ``endoflow reconstruct`` prepares its input frames with it, so K and
the pixels agree wherever a model runs. RGB is centre-cropped to a square and resized with ``cv2.INTER_AREA``;
depth by nearest neighbour with pixel centres aligned (``cv2.INTER_NEAREST_EXACT``), so no depth value is
invented across an edge. Imports no reader and no writer.
"""

from __future__ import annotations

import cv2
import numpy as np

from endoflow.geometry.camera import scale_intrinsics


def centre_square(height: int, width: int) -> tuple[int, int, int]:
    """``(top, left, side)`` of the largest centred square."""
    side = min(height, width)
    return (height - side) // 2, (width - side) // 2, side


def stored_intrinsics(K: np.ndarray, native_size: tuple[int, int], size: int) -> np.ndarray:
    """K of the native image after the centre crop to a square and the resize to ``size x size``."""
    top, left, side = centre_square(*native_size)
    cropped = np.array(K, dtype=np.float64)
    cropped[0, 2] -= left
    cropped[1, 2] -= top
    scale = size / side
    return scale_intrinsics(cropped, scale, scale)


def resize_rgb(rgb: np.ndarray, size: int) -> np.ndarray:
    top, left, side = centre_square(*rgb.shape[:2])
    square = rgb[top : top + side, left : left + side]
    return cv2.resize(square, (size, size), interpolation=cv2.INTER_AREA)


def resize_depth(depth: np.ndarray, size: int) -> np.ndarray:
    top, left, side = centre_square(*depth.shape[:2])
    square = np.ascontiguousarray(depth[top : top + side, left : left + side])
    # NEAREST_EXACT samples the source pixel under each target pixel's centre (plain NEAREST is off by
    # half a pixel), keeping depth registered with the INTER_AREA colour image and K.
    return cv2.resize(square, (size, size), interpolation=cv2.INTER_NEAREST_EXACT)


def depth_to_counts(depth_cm: np.ndarray, unit: float) -> tuple[np.ndarray, int]:
    """``uint16`` counts of ``unit`` cm; non-finite, non-positive and out-of-range depths become 0."""
    counts = np.round(np.nan_to_num(depth_cm, nan=0.0, posinf=0.0, neginf=0.0) / unit)
    too_far = counts > np.iinfo(np.uint16).max
    counts[too_far | (counts < 0)] = 0
    return counts.astype(np.uint16), int(too_far.sum())


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an RGB ``uint8`` or single-channel ``uint16`` image."""
    pixels = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    ok, data = cv2.imencode(".png", pixels)
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {image.shape}, {image.dtype}")
    return data.tobytes()

"""Which part of an input frame the model sees: a region of it (``--crop x,y,w,h``, else the whole frame), then
the centred square of that region, resized to the model's size as preprocessing does for training
(:mod:`endoflow.data.frame_encoding`).

A frame far from square loses much to that square: a 384x192 side-by-side frame (two views, or an image beside
another method's depth map) keeps only its middle half, made of the inner halves of both views.
:func:`crop_warning` says so, and ``--crop`` picks one view.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from endoflow.data.frame_encoding import centre_square
from endoflow.errors import DataFormatError

# A frame more elongated than this loses over a third of itself to the square the model sees: say so.
ELONGATED_ASPECT = 1.5


@dataclass(frozen=True)
class Crop:
    """A region of the native frames in pixels: top-left corner ``x, y``, size ``width x height``."""

    x: int
    y: int
    width: int
    height: int

    @classmethod
    def parse(cls, spec: str) -> "Crop":
        """``"x,y,width,height"`` (``--crop``) in whole pixels."""
        try:
            x, y, width, height = (int(value) for value in spec.split(","))
        except ValueError:
            raise ValueError(f"--crop: expected x,y,width,height in whole pixels, got {spec!r}") from None
        if x < 0 or y < 0 or width < 1 or height < 1:
            raise ValueError(f"--crop {spec}: x and y must be >= 0, width and height >= 1")
        return cls(x, y, width, height)

    @property
    def size(self) -> tuple[int, int]:
        """``(height, width)``, as frame sizes are given."""
        return self.height, self.width

    def __str__(self) -> str:
        return f"{self.width}x{self.height} px at x={self.x}, y={self.y}"


def frame_region(native_size: tuple[int, int], crop: Optional[Crop], source: str) -> Crop:
    """The region of ``native_size`` (height, width) frames that ``crop`` selects (None: the whole frame).

    Raises:
        DataFormatError: naming ``source``, for a crop reaching beyond the frames.
    """
    height, width = native_size
    if crop is None:
        return Crop(0, 0, width, height)
    if crop.x + crop.width > width or crop.y + crop.height > height:
        raise DataFormatError(source, f"--crop {crop.x},{crop.y},{crop.width},{crop.height} reaches beyond the "
                                      f"{width}x{height} px frames")
    return crop


def model_view(region: Crop) -> Crop:
    """The square of the native frame the model sees: the centred square of ``region``."""
    top, left, side = centre_square(region.height, region.width)
    return Crop(region.x + left, region.y + top, side, side)


def crop_image(image: np.ndarray, region: Crop) -> np.ndarray:
    """The part of ``image`` (rows, columns, ...) inside ``region``."""
    return image[region.y : region.y + region.height, region.x : region.x + region.width]


def crop_intrinsics(K: np.ndarray, region: Crop) -> np.ndarray:
    """K of the frames cut to ``region``: the principal point moves by the region's corner."""
    cropped = np.array(K, dtype=np.float64)
    cropped[0, 2] -= region.x
    cropped[1, 2] -= region.y
    return cropped


def crop_warning(native_size: tuple[int, int], region: Crop, source: str) -> Optional[str]:
    """A warning when ``region`` is far from square (aspect above :data:`ELONGATED_ASPECT`): the square the model
    sees, the share of each frame it drops, and how to pick a part with ``--crop``; else None."""
    if max(region.width, region.height) <= ELONGATED_ASPECT * min(region.width, region.height):
        return None
    view = model_view(region)
    height, width = native_size
    dropped = 1 - view.width * view.height / (width * height)
    of = "" if region.size == native_size else f" of the --crop region {region}"
    first = f"0,0,{width // 2},{height}" if region.width > region.height else f"0,0,{width},{height // 2}"
    return (f"{source}: frames of {width}x{height} px: the model sees only the centre square {view}{of}, "
            f"{dropped:.0%} of each frame is dropped; if a frame holds two views side by side (stereo, or an image "
            f"beside a depth map), pick one with --crop x,y,width,height (--crop {first} for the first)")

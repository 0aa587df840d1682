"""The field of view of an endoscope's frames: the pixels that see the scene, not the black border around it.

An endoscope's image is a circle (or an octagon) in a black frame, sometimes with black bands beside it. That
border is black in every frame and touches the image's edge; the lumen is dark too, but it lies inside and lights
up as the camera moves. So a pixel is outside the field of view where it stays black (every channel at most
``BLACK_LEVEL``) in every frame looked at, and belongs to a black region that touches the image's edge; the
border's blurred rim is left out too (``RIM_PX``). Of what remains, the largest connected region is the field of
view: text or a timestamp burnt into the border is not. Found once per sequence, from its frames; a field of view
smaller than ``MIN_SHARE`` of the image (frames black throughout, a recording that opens in the dark) is refused.
"""

from __future__ import annotations

from typing import Iterable

import cv2
import numpy as np

from endoflow.data.frame_encoding import centre_square

# of 255: the black of the border, above its compression noise, below a dark lumen's wall (a frame-by-frame test
# of a single pixel, as the tracker's, needs a lower one: it has no other frames to light the pixel up)
BLACK_LEVEL = 12
RIM_PX = 2  # the border's blurred edge, left out with it
FIELD_OF_VIEW_FRAMES = 60  # the frames it is found in: its border is black in every one
# An endoscope's circle fills about 0.7 to 0.95 of its frame; a fifth is no field of view but frames that stay dark.
MIN_SHARE = 0.2


class NoFieldOfView(ValueError):
    """The frames looked at are black nearly everywhere: no field of view can be found in them."""


def field_of_view(frames: Iterable[np.ndarray]) -> np.ndarray:
    """``H x W`` bool, True where the frames (``H x W x 3`` uint8, at least one) see the scene.

    Raises:
        NoFieldOfView: it would cover less than :data:`MIN_SHARE` of the image.
        ValueError: no frames, a frame that is not ``H x W x 3`` uint8, or frames of different sizes.
    """
    # per pixel and channel over the frames; the channels are reduced once, at the end: a per-frame max over the
    # last axis of a 1080p frame costs 40 ms, an elementwise maximum 0.2 ms
    brightest: np.ndarray | None = None
    for frame in frames:
        if frame.ndim != 3 or frame.dtype != np.uint8:
            raise ValueError(f"field of view: expected H x W x 3 uint8 frames, got {frame.dtype} {frame.shape}")
        if brightest is None:
            brightest = frame.copy()
        elif frame.shape != brightest.shape:
            raise ValueError(f"field of view: frames of different sizes, {brightest.shape} and {frame.shape}")
        else:
            np.maximum(brightest, frame, out=brightest)
    if brightest is None:
        raise ValueError("field of view: no frames to find it in")
    black = (brightest.max(axis=2) <= BLACK_LEVEL).astype(np.uint8)
    _, labels = cv2.connectedComponents(black, connectivity=8)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    border = np.isin(labels, edge[edge > 0])
    if RIM_PX and border.any():
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * RIM_PX + 1, 2 * RIM_PX + 1))
        border = cv2.dilate(border.astype(np.uint8), kernel) > 0
    valid = largest_region(~border)
    if valid.mean() < MIN_SHARE:
        raise NoFieldOfView(f"the frames are black (every channel at most {BLACK_LEVEL} of 255) over "
                            f"{1 - valid.mean():.0%} of the image; expected an endoscope's field of view of at least "
                            f"{MIN_SHARE:.0%} of it (do the frames start in the dark, or is the video black?)")
    return valid


def largest_region(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected region of a bool ``mask`` (all False when it has none)."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if count <= 1:
        return np.zeros_like(mask, dtype=bool)
    return labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))


def resized_field_of_view(valid: np.ndarray, size: int) -> np.ndarray:
    """The field of view of ``valid`` after the centre crop to a square and the resize to ``size`` that frames get
    (:mod:`endoflow.data.frame_encoding`): a pixel is in where all it averages over is."""
    top, left, side = centre_square(*valid.shape)
    square = valid[top:top + side, left:left + side].astype(np.float32)
    return cv2.resize(square, (size, size), interpolation=cv2.INTER_AREA) > 0.999

"""The field of view: the black border around an endoscope's image is found and left out, a dark lumen is not."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from endoflow.data.field_of_view import (BLACK_LEVEL, MIN_SHARE, RIM_PX, NoFieldOfView, field_of_view,
                                         resized_field_of_view)
from endoflow.reconstruction.frames import FrameRange, VideoFrames
from tests.samples import COLONOSCOPY_CLIP

SIZE = 96


def scene_frames(count: int = 8, seed: int = 0) -> list[np.ndarray]:
    """Textured frames that change from one to the next, with a lumen (a dark disc, moving) inside."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(count):
        frame = rng.integers(60, 220, (SIZE, SIZE, 3)).astype(np.uint8)
        cv2.circle(frame, (40 + i, 45), 10, (3, 2, 2), -1)  # the lumen: as black as the border
        frames.append(frame)
    return frames


def circle(radius: float) -> np.ndarray:
    v, u = np.mgrid[:SIZE, :SIZE]
    return (u - (SIZE - 1) / 2) ** 2 + (v - (SIZE - 1) / 2) ** 2 <= radius**2


def test_a_circular_field_of_view_is_found_and_its_rim_left_out():
    inside = circle(40)
    frames = [frame * inside[..., None].astype(np.uint8) for frame in scene_frames()]
    valid = field_of_view(frames)
    assert not valid[0, 0] and not valid[-1, -1] and valid[SIZE // 2, SIZE // 2]
    assert (valid <= inside).all()  # nothing outside the circle
    assert valid[circle(40 - RIM_PX - 1)].all()  # everything inside but the rim


def test_a_dark_lumen_stays_in_the_field_of_view():
    frames = [frame * circle(40)[..., None].astype(np.uint8) for frame in scene_frames()]
    lumen = np.zeros((SIZE, SIZE), np.uint8)
    cv2.circle(lumen, (43, 45), 6, 1, -1)  # black in every frame (the lumen moves by 7 px)
    assert field_of_view(frames)[lumen > 0].all()


def test_frames_without_a_border_are_all_in_view_and_bad_input_is_refused():
    assert field_of_view(scene_frames()).all()
    with pytest.raises(ValueError, match="no frames"):
        field_of_view([])
    with pytest.raises(ValueError, match="uint8"):
        field_of_view([np.zeros((4, 4), np.float32)])
    first, second = scene_frames(2)
    with pytest.raises(ValueError, match=r"different sizes, \(96, 96, 3\) and \(96, 95, 3\)"):
        field_of_view([first, second[:, 1:]])


def test_a_pixel_lit_in_any_channel_of_any_frame_is_in_view():
    frames = [frame * circle(40)[..., None].astype(np.uint8) for frame in scene_frames(3)]
    for frame in frames:
        frame[38:59, 2:21] = 0  # a dark bay of the border reaching into the circle
    frames[0][40:48, 12:21, 0] = BLACK_LEVEL + 1  # part of it lit in red in one frame, part in blue in another
    frames[1][48:57, 12:21, 2] = BLACK_LEVEL + 1
    valid = field_of_view(frames)
    assert valid[44, 16] and valid[52, 16] and not valid[39, 16]


def test_text_burnt_into_the_border_is_not_part_of_the_field_of_view():
    frames = [frame * circle(40)[..., None].astype(np.uint8) for frame in scene_frames()]
    for frame in frames:
        cv2.putText(frame, "12:04", (0, 8), cv2.FONT_HERSHEY_PLAIN, 0.6, (255, 255, 255), 1)  # a timestamp
    valid = field_of_view(frames)
    assert not valid[:8, :12].any() and valid[circle(40 - RIM_PX - 1)].all()


def test_frames_that_stay_black_have_no_field_of_view_and_say_so():
    frames = [np.zeros((SIZE, SIZE, 3), np.uint8) for _ in range(3)]
    frames[0][40:50, 40:50] = 200  # a speck of light: far below the smallest field of view
    with pytest.raises(NoFieldOfView, match=rf"black .* over \d+% of the image; expected .* at least {MIN_SHARE:.0%}"):
        field_of_view(frames)


def test_resizing_keeps_only_what_lies_wholly_inside():
    valid = np.zeros((10, 20), bool)
    valid[:, 5:15] = True  # the centre square is columns 5-14: all in view
    assert resized_field_of_view(valid, 5).all()
    valid[0, 5] = False
    small = resized_field_of_view(valid, 5)
    assert not small[0, 0] and small.sum() == 24


@pytest.mark.skipif(not COLONOSCOPY_CLIP.is_file(), reason=f"real colonoscopy clip not found at {COLONOSCOPY_CLIP}")
def test_the_real_clips_circular_field_of_view_is_found():
    from endoflow.data.crop import Crop, frame_region

    source = VideoFrames(COLONOSCOPY_CLIP)
    region = frame_region(source.native_size, Crop(0, 0, 192, 192), str(COLONOSCOPY_CLIP))
    frames = [frame.cropped(region).rgb for frame, _ in zip(source.frames(FrameRange()), range(60))]
    valid = field_of_view(frames)
    # a circle cut by the square's sides: the four corners out (about 7 % of the frame), the rest in
    assert 0.85 < valid.mean() < 0.97
    assert not valid[0, 0] and not valid[0, -1] and not valid[-1, 0] and not valid[-1, -1]
    assert valid[96, 96] and valid[96, 10] and valid[10, 96]

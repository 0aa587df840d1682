"""Image IO: bit depth and channel order checked, exact 16-bit -> 8-bit colour, atomic writes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from endoflow.data.imageio import image_size, read_png8_gray, read_gray16, read_rgb, write_png
from endoflow.errors import DataFormatError

RNG = np.random.default_rng(3)
RGB = RNG.integers(0, 256, size=(6, 9, 3), dtype=np.uint8)


def test_rgb_round_trip_keeps_channel_order(tmp_path):
    write_png(tmp_path / "a.png", RGB)
    np.testing.assert_array_equal(read_rgb(tmp_path / "a.png"), RGB)
    bgr_on_disk = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(bgr_on_disk[..., ::-1], RGB)


@pytest.mark.parametrize("alpha", [65280, 65535])
def test_16bit_rgba_gives_the_exact_8bit_values(tmp_path, alpha):
    rgba16 = np.concatenate([RGB.astype(np.uint16) * 256, np.full((6, 9, 1), alpha, np.uint16)], axis=-1)
    write_png(tmp_path / "frame.png", rgba16)
    assert cv2.imread(str(tmp_path / "frame.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    np.testing.assert_array_equal(read_rgb(tmp_path / "frame.png"), RGB)


def test_16bit_grey_round_trip_and_size_from_header(tmp_path):
    depth = RNG.integers(0, 65536, size=(5, 7), dtype=np.uint16)
    write_png(tmp_path / "d.png", depth)
    np.testing.assert_array_equal(read_gray16(tmp_path / "d.png"), depth)
    assert image_size(tmp_path / "d.png") == (5, 7)


def test_png16_refuses_8bit_and_colour(tmp_path):
    write_png(tmp_path / "eight.png", np.zeros((4, 4), np.uint8))
    with pytest.raises(DataFormatError, match="16-bit single-channel PNG, found uint8 with 1 channel") as info:
        read_gray16(tmp_path / "eight.png")
    assert info.value.path == tmp_path / "eight.png"
    write_png(tmp_path / "colour.png", np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(DataFormatError, match="found uint16 with 3 channel"):
        read_gray16(tmp_path / "colour.png")


def test_gray8_accepts_equal_channels_only(tmp_path):
    level = RNG.integers(0, 256, size=(4, 5), dtype=np.uint8)
    write_png(tmp_path / "g.png", np.dstack([level, level, level, np.full_like(level, 255)]))
    np.testing.assert_array_equal(read_png8_gray(tmp_path / "g.png"), level)
    write_png(tmp_path / "c.png", RGB)
    with pytest.raises(DataFormatError, match="equal colour channels"):
        read_png8_gray(tmp_path / "c.png")


def test_rgb_refuses_grey_files(tmp_path):
    write_png(tmp_path / "g.png", np.zeros((4, 4), np.uint8))
    with pytest.raises(DataFormatError, match=r"expected a colour image \(3 or 4 channels\), found uint8 with 1"):
        read_rgb(tmp_path / "g.png")


def test_missing_and_unreadable_files_name_the_file(tmp_path):
    with pytest.raises(DataFormatError, match="image file not found") as info:
        read_rgb(tmp_path / "nope.png")
    assert info.value.path == tmp_path / "nope.png"
    (tmp_path / "bad.png").write_bytes(b"not a png at all")
    with pytest.raises(DataFormatError, match="unreadable image"):
        read_gray16(tmp_path / "bad.png")


def test_write_refuses_unsupported_arrays(tmp_path):
    with pytest.raises(ValueError, match="expected HxW, HxWx3 or HxWx4"):
        write_png(tmp_path / "x.png", np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(ValueError, match="expected HxW, HxWx3 or HxWx4"):
        write_png(tmp_path / "x.png", np.zeros((4, 4), np.float32))
    assert list(tmp_path.iterdir()) == []


def test_interrupted_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "x.png"
    write_png(target, RGB)

    def fail(*_):
        raise OSError("disk full")

    monkeypatch.setattr("endoflow.io.os.replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_png(target, np.zeros_like(RGB))
    monkeypatch.undo()
    np.testing.assert_array_equal(read_rgb(target), RGB)
    assert [p.name for p in tmp_path.iterdir()] == ["x.png"]

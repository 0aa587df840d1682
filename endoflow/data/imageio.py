"""Image files in and out, with the bit depth and channel order checked rather than guessed.

Everything decodes with ``IMREAD_UNCHANGED`` (OpenCV's default flag turns 16-bit PNGs into 8-bit BGR) and
uses RGB(A) order outside this module; every problem raises :class:`~endoflow.errors.DataFormatError`
naming the file.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from endoflow.errors import DataFormatError
from endoflow.io import write_bytes

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _decode_unchanged(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DataFormatError(path, "image file not found")
    # imdecode on the bytes (not imread) so paths with non-ASCII characters work on every platform.
    data = np.fromfile(path, dtype=np.uint8)
    # libtiff warns about tags it does not need (C3VD's depth TIFFs: a NUL in ImageDescription) on every read
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if image is None:
        raise DataFormatError(path, "unreadable image: the file cannot be decoded (truncated or not an image)")
    return image


def _channels(image: np.ndarray) -> int:
    return 1 if image.ndim == 2 else image.shape[2]


def _describe(image: np.ndarray) -> str:
    return f"{image.dtype} with {_channels(image)} channel(s), shape {image.shape}"


def read_rgb(path: str | Path) -> np.ndarray:
    """Colour image as ``H x W x 3`` ``uint8`` RGB.

    Accepts 8- or 16-bit files with 3 (BGR as OpenCV decodes) or 4 channels (alpha is dropped). 16-bit
    samples keep their high byte, which is exact for SimCol3D's FrameBuffer PNGs (8-bit values times 256).

    Raises:
        DataFormatError: file missing or undecodable, not a colour image, or neither 8 nor 16 bits.
    """
    path = Path(path)
    image = _decode_unchanged(path)
    if _channels(image) not in (3, 4):
        raise DataFormatError(path, f"expected a colour image (3 or 4 channels), found {_describe(image)}")
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise DataFormatError(path, f"expected an 8- or 16-bit colour image, found {_describe(image)}")
    code = cv2.COLOR_BGRA2RGB if _channels(image) == 4 else cv2.COLOR_BGR2RGB
    return cv2.cvtColor(image, code)


def read_gray16(path: str | Path) -> np.ndarray:
    """``H x W`` ``uint16`` single-channel image (depth maps: PNG, TIFF); anything else is an error, never converted.

    Raises:
        DataFormatError: missing or undecodable, or not 16-bit single channel (names the dtype found).
    """
    path = Path(path)
    image = _decode_unchanged(path)
    if image.dtype != np.uint16 or _channels(image) != 1:
        kind = path.suffix.lstrip(".").upper() or "image"
        raise DataFormatError(path, f"expected a 16-bit single-channel {kind}, found {_describe(image)}")
    return image


def read_png8_gray(path: str | Path) -> np.ndarray:
    """``H x W`` ``uint8`` grey image; colour files are accepted only when R, G and B are equal.

    EndoSLAM's UnityCam depth maps are 8-bit RGBA with equal colour channels; unequal channels mean the
    file is not a grey map and would be misread.

    Raises:
        DataFormatError: missing or undecodable, not 8-bit, or colour with unequal channels.
    """
    path = Path(path)
    image = _decode_unchanged(path)
    if image.dtype != np.uint8:
        raise DataFormatError(path, f"expected an 8-bit grey image, found {_describe(image)}")
    if _channels(image) == 1:
        return image
    colour = image[..., :3]
    if not (np.array_equal(colour[..., 0], colour[..., 1]) and np.array_equal(colour[..., 0], colour[..., 2])):
        raise DataFormatError(path, f"expected a grey image (equal colour channels), found {_describe(image)}")
    return np.ascontiguousarray(colour[..., 0])


def image_size(path: str | Path) -> tuple[int, int]:
    """``(height, width)`` of an image; PNGs are measured from their header without decoding."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "image file not found")
    with open(path, "rb") as handle:
        header = handle.read(24)
    if header[:8] == _PNG_SIGNATURE and header[12:16] == b"IHDR":
        width, height = struct.unpack(">II", header[16:24])
        return int(height), int(width)
    image = _decode_unchanged(path)
    return int(image.shape[0]), int(image.shape[1])


def write_png(path: str | Path, array: np.ndarray) -> None:
    """Write ``array`` as PNG atomically (through :mod:`endoflow.io`).

    ``array``: ``H x W`` grey or ``H x W x 3`` RGB or ``H x W x 4`` RGBA, ``uint8`` or ``uint16``.
    A reader never sees a half-written file, and a failed write leaves the old file (if any) untouched.
    """
    path = Path(path)
    array = np.asarray(array)
    shape_ok = array.ndim == 2 or (array.ndim == 3 and array.shape[2] in (1, 3, 4))
    if array.dtype not in (np.uint8, np.uint16) or not shape_ok:
        raise ValueError(
            f"write_png {path}: expected HxW, HxWx3 or HxWx4 uint8/uint16, got {array.dtype} {array.shape}"
        )
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    if array.ndim == 3:
        array = cv2.cvtColor(array, cv2.COLOR_RGB2BGR if array.shape[2] == 3 else cv2.COLOR_RGBA2BGRA)
    ok, encoded = cv2.imencode(".png", array)
    if not ok:
        raise ValueError(f"write_png {path}: OpenCV could not encode {_describe(array)}")
    write_bytes(path, encoded.tobytes(), durable=False)

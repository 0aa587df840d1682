"""Small pieces shared by the native-layout readers: numbered file listings, intrinsics validation."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from endoflow.data.base import DataFormatError


def natural_key(text: str) -> tuple:
    """Sort key that orders embedded numbers by value: ``S2`` before ``S10``, ``25`` before ``100``."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text))


def numbered_files(folder: Path, pattern: str) -> dict[int, Path]:
    """Files in ``folder`` whose names fully match ``pattern`` (one group: the frame number), by number.

    Raises:
        DataFormatError: two files carry the same number (``frame_1.png`` and ``frame_01.png``).
    """
    regex = re.compile(pattern)
    found: dict[int, Path] = {}
    for path in folder.iterdir():
        match = regex.fullmatch(path.name)
        if match is None or not path.is_file():
            continue
        number = int(match.group(1))
        if number in found:
            raise DataFormatError(folder, f"frame number {number} appears twice: {found[number].name}, {path.name}")
        found[number] = path
    return dict(sorted(found.items()))


def subfolders(folder: Path, skip: Sequence[str] = ()) -> list[Path]:
    """Visible subfolders of ``folder`` in natural order, without the names in ``skip``."""
    return sorted(
        (p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name not in skip),
        key=lambda p: natural_key(p.name),
    )


def checked_intrinsics(values: Sequence[Sequence[float]] | np.ndarray, source: str | Path) -> np.ndarray:
    """A 3x3 float64 pixel K, checked for shape, positive focal lengths and a last row of ``0 0 1``.

    The last-row check catches a transposed (column-major) K, the usual way a K file is misread.

    Raises:
        DataFormatError: naming ``source`` (a file or a parameter name) and what is wrong.
    """
    try:
        K = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(source, f"intrinsics are not numbers: {exc}") from None
    if K.shape != (3, 3):
        raise DataFormatError(source, f"expected a 3x3 intrinsics matrix, found shape {K.shape}")
    if not np.isfinite(K).all() or not np.allclose(K[2], [0, 0, 1]) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataFormatError(
            source, f"expected K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, found {K.tolist()}"
        )
    return K


def frame_gap_note(numbers: Sequence[int]) -> Optional[str]:
    """A short note on gaps in sorted frame numbers (``None`` when contiguous)."""
    expected = set(range(numbers[0], numbers[-1] + 1))
    missing = sorted(expected - set(numbers))
    if not missing:
        return None
    shown = ", ".join(map(str, missing[:5])) + (" ..." if len(missing) > 5 else "")
    return f"frame numbers not contiguous: {len(missing)} missing ({shown})"


def checked_size(path: Path, array: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``array`` unchanged if its height and width are ``size``; else an error naming ``path``."""
    if array.shape[:2] != tuple(size):
        raise DataFormatError(path, f"image size {array.shape[:2]} differs from the sequence's {tuple(size)}")
    return array


def ray_length_to_z_factor(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """``H x W`` float32 ``1 / |K^-1 [u v 1]|``: multiply a distance along the pixel's ray by it to get z-depth."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    return (1.0 / np.linalg.norm(rays, axis=0)).reshape(height, width).astype(np.float32)


def sized_loader(
    paths: Sequence[Path], size: tuple[int, int], decode: Callable[[Path], np.ndarray]
) -> Callable[[int], np.ndarray]:
    """``i -> decode(paths[i])``, checking that every frame has the sequence's ``(height, width)``."""

    def load(i: int) -> np.ndarray:
        return checked_size(paths[i], decode(paths[i]), size)

    return load

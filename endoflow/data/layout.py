"""Small pieces shared by the native-layout readers: numbered file listings, intrinsics validation,
reporting of non-fatal problems (frame gaps, non-finite pose values)."""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from endoflow.data.base import missing_frame_ids
from endoflow.errors import DataFormatError
from endoflow.geometry.pose import quaternion_xyzw_to_matrix

SHOWN_NUMBERS = 5


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


def report(problems: list[str], path: Path, note: str) -> None:
    """Warn ``<path>: <note>`` and keep ``<file name>: <note>`` in a sequence's ``problems``."""
    warnings.warn(f"{path}: {note}", stacklevel=3)
    problems.append(f"{path.name}: {note}")


def report_frame_gaps(problems: list[str], folder: Path, sequence: str, frame_ids: list[int]) -> None:
    """Report frame numbers missing inside a sequence, once: neighbours (prev/next) never span them."""
    missing = missing_frame_ids(frame_ids)
    if missing:
        report(
            problems,
            folder,
            f"sequence {sequence}: frame numbers not contiguous, {len(missing)} missing "
            f"({shown_numbers(missing)}); no sample spans the gap",
        )


def report_non_finite_rows(problems: list[str], path: Path, rows: np.ndarray, frame_ids: list[int]) -> None:
    """Report the frames whose pose values read from ``path`` (one row per frame) are NaN or infinite.

    :func:`pose_matrices` gives those frames no pose.
    """
    bad = ~np.isfinite(rows).all(axis=1)
    if bad.any():
        frames = [frame_ids[i] for i in np.flatnonzero(bad)]
        report(problems, path, f"non-finite pose values (NaN or inf) for {len(frames)} frame(s) "
                               f"({shown_numbers(frames)}); those frames have no pose")


def pose_matrices(translations: np.ndarray, quaternions: np.ndarray) -> np.ndarray:
    """``N x 4 x 4`` ``[[R(q), t], [0, 1]]`` from ``N x 3`` translations and ``N x 4`` xyzw quaternions.

    Rows with a NaN or infinite value give all-NaN matrices (frames without a pose).
    """
    poses = np.tile(np.eye(4), (len(translations), 1, 1))
    known = np.isfinite(translations).all(axis=1) & np.isfinite(quaternions).all(axis=1)
    poses[~known] = np.nan
    poses[known, :3, :3] = quaternion_xyzw_to_matrix(quaternions[known])
    poses[known, :3, 3] = translations[known]
    return poses


def shown_numbers(numbers: Sequence[int]) -> str:
    """The first few of ``numbers``, comma-separated, with `` ...`` when there are more."""
    shown = ", ".join(map(str, numbers[:SHOWN_NUMBERS]))
    return shown + (" ..." if len(numbers) > SHOWN_NUMBERS else "")


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

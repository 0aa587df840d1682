"""What every dataset reader produces: sequences of frames in one convention, and the error for bad input.

RGB ``uint8``, z-depth in cm (0 = no reading), poses ``T_world_cam`` (OpenCV, cm; ``None`` where unknown), pixel K
at the stored size. Readers convert at this boundary and raise :class:`DataFormatError` naming the file. See
docs/datasets.md (conventions, reported problems) and docs/architecture.md, "Conventions".
"""

from __future__ import annotations

import re
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from endoflow.config import DATASETS, DEPTH_ONLY_DATASETS  # noqa: F401  (re-exported: readers' names)
from endoflow.data.field_of_view import FIELD_OF_VIEW_FRAMES, NoFieldOfView, field_of_view
from endoflow.errors import DataFormatError


@dataclass
class Frame:
    """One decoded frame in the common convention (see module docstring)."""

    rgb: np.ndarray
    depth_cm: Optional[np.ndarray]
    T_world_cam: Optional[np.ndarray]
    K: np.ndarray


@dataclass
class Sequence:
    """A contiguous recording: lazily loaded frames sharing one camera.

    Attributes:
        dataset: reader name, one of :data:`DATASETS`.
        name: sequence name, unique within the dataset (``S5``, ``UnityCam/Colon``, ``train/0/223``).
        split: ``train``, ``val`` or ``test``.
        K: 3x3 pixel intrinsics for ``image_size``.
        image_size: ``(height, width)`` of the stored frames.
        frame_ids: the dataset's own frame numbers, in temporal order.
        poses: ``N x 4 x 4`` ``T_world_cam`` (NaN-filled where a frame has no pose), or ``None``.
        load_rgb: ``i -> H x W x 3 uint8`` for the i-th frame (position, not frame id); ``None`` for
            depth-only datasets.
        load_depth: ``i -> H x W float32`` z-depth in cm, or ``None`` when the dataset has no depth.
        group: coarser grouping for test sets (``SyntheticColon_III``, ``Colon``...).
        problems: non-fatal issues found while reading (shown by ``endoflow data inspect``).
        source_files: per position, the files that frame is decoded from (RGB, depth); what a derived
            product built from the frame must be rebuilt after (see :meth:`frame_files`). Empty for
            sources that do not read files (frames made in memory).
        intrinsics_known: whether ``K`` was given (a calibration, a dataset's file) or assumed for a camera
            nobody calibrated (:mod:`endoflow.data.video`); shards say so, and training can learn it.
    """

    dataset: str
    name: str
    split: str
    K: np.ndarray
    image_size: tuple[int, int]
    frame_ids: list[int]
    poses: Optional[np.ndarray]
    load_rgb: Optional[Callable[[int], np.ndarray]]
    load_depth: Optional[Callable[[int], np.ndarray]]
    group: str = ""
    problems: list[str] = field(default_factory=list)
    source_files: list[tuple[Path, ...]] = field(default_factory=list)
    intrinsics_known: bool = True
    _valid: Optional[np.ndarray] = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.source_files and len(self.source_files) != len(self.frame_ids):
            raise ValueError(
                f"sequence {self.name}: source_files lists {len(self.source_files)} frames, "
                f"frame_ids {len(self.frame_ids)}"
            )

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def frame_step(self) -> int:
        """The regular difference between consecutive frame numbers (see :func:`frame_step`)."""
        return frame_step(self.frame_ids)

    def frame_files(self, i: int) -> list[Path]:
        """The files the i-th frame is decoded from; empty when the sequence is not read from files."""
        return list(self.source_files[i]) if self.source_files else []

    def pose(self, i: int) -> Optional[np.ndarray]:
        """``T_world_cam`` of the i-th frame, or ``None`` where unknown."""
        if self.poses is None or not np.isfinite(self.poses[i]).all():
            return None
        return self.poses[i]

    def field_of_view(self) -> np.ndarray:
        """``H x W`` bool: where the sequence's frames see the scene (:mod:`endoflow.data.field_of_view`), found in
        up to :data:`~endoflow.data.field_of_view.FIELD_OF_VIEW_FRAMES` frames spread over it, once."""
        if self._valid is None:
            if self.load_rgb is None:
                raise DataFormatError(self.name, f"{self.dataset} sequence has no RGB frames to find a field of "
                                                 f"view in")
            count = min(len(self), FIELD_OF_VIEW_FRAMES)
            positions = np.linspace(0, len(self) - 1, count).round().astype(int)
            try:
                self._valid = field_of_view(self.load_rgb(int(i)) for i in positions)
            except NoFieldOfView as exc:
                raise DataFormatError(f"{self.dataset}/{self.name}", str(exc)) from None
        return self._valid

    def frame(self, i: int) -> Frame:
        """Decode the i-th frame (position in the sequence, not the dataset's frame id)."""
        rgb = self.load_rgb(i) if self.load_rgb is not None else None
        depth = self.load_depth(i) if self.load_depth is not None else None
        return Frame(rgb=rgb, depth_cm=depth, T_world_cam=self.pose(i), K=self.K)


def frame_step(frame_ids: list[int]) -> int:
    """The smallest difference between consecutive sorted frame numbers (1 for fewer than two frames).

    Datasets number frames 0, 1, 2, ... (SimCol3D, EndoSLAM) or 0, 25, 50, ... (SceneNet); a larger
    difference somewhere is a gap: frames are missing there.
    """
    differences = [b - a for a, b in zip(frame_ids, frame_ids[1:])]
    return min(differences) if differences else 1


def missing_frame_ids(frame_ids: list[int]) -> list[int]:
    """Frame numbers absent from the regular run ``first, first + step, ..., last`` (:func:`frame_step`)."""
    if not frame_ids:
        return []
    step = frame_step(frame_ids)
    return sorted(set(range(frame_ids[0], frame_ids[-1] + 1, step)) - set(frame_ids))


def slug(text: str) -> str:
    """``text`` with anything but ASCII letters, digits, ``_`` and ``-`` made ``_``.

    Safe as one file name and inside a WebDataset key (which is split at its first dot, and where ``/``
    would make a folder); used wherever a sequence name becomes part of a name.
    """
    return re.sub(r"[^A-Za-z0-9_-]", "_", text)


class DatasetReader(ABC):
    """Turns one dataset's native layout under ``root`` into :class:`Sequence` objects."""

    name: str = ""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataFormatError(self.root, f"{self.name} root folder not found")

    @abstractmethod
    def sequences(self) -> list[Sequence]:
        """All sequences found under ``root``, sorted by name; raises on a broken layout."""

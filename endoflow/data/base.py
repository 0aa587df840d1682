"""What every dataset reader produces: sequences of frames in one convention.

Conventions (the same everywhere downstream, so nothing needs to know where data came from):

- RGB: ``H x W x 3`` ``uint8``, RGB channel order.
- Depth: ``H x W`` ``float32`` z-depth in centimetres (distance along the optical axis, not ray length);
  ``0`` where there is no reading.
- Pose: ``4 x 4`` ``float64`` camera-to-world ``T_world_cam`` in the OpenCV camera convention (x right,
  y down, z forward), right-handed, translation in centimetres. ``None`` where the dataset has no pose.
- K: ``3 x 3`` pixel intrinsics for the stored image size, pixel centres at integer coordinates.

Readers convert at this boundary (SimCol's left-handed Unity poses, SceneNet's ray-length depth in mm,
EndoSLAM's units) and raise :class:`DataFormatError` naming the file and what was expected when input
does not match the documented layout.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np


class DataFormatError(ValueError):
    """Input does not match the documented layout. The message names the file and what was expected."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")

    def __reduce__(self):
        # Default exception pickling replays args (the joined message) into __init__, which takes two:
        # without this, an error raised in a worker process reaches the parent as a broken pool.
        return (type(self), (str(self.path), self.problem))


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
        dataset: reader name (``simcol``, ``endoslam``, ``scenenet``).
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

    def __len__(self) -> int:
        return len(self.frame_ids)

    def pose(self, i: int) -> Optional[np.ndarray]:
        """``T_world_cam`` of the i-th frame, or ``None`` where unknown."""
        if self.poses is None or not np.isfinite(self.poses[i]).all():
            return None
        return self.poses[i]

    def frame(self, i: int) -> Frame:
        """Decode the i-th frame (position in the sequence, not the dataset's frame id)."""
        rgb = self.load_rgb(i) if self.load_rgb is not None else None
        depth = self.load_depth(i) if self.load_depth is not None else None
        return Frame(rgb=rgb, depth_cm=depth, T_world_cam=self.pose(i), K=self.K)


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

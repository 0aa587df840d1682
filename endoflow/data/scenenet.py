"""SceneNet RGB-D reader (depth for the latent-bank pretraining), in the common convention of ``base``.

Turns the millimetres of ray length into z-depth in cm with K from the camera's field of view; reads no poses.
See docs/datasets.md, "SceneNet RGB-D".
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np

from endoflow.config import SceneNetConfig
from endoflow.data.base import DatasetReader, Sequence
from endoflow.data.imageio import image_size, read_gray16, read_rgb
from endoflow.data.layout import checked_size, natural_key, numbered_files, ray_length_to_z_factor, sized_loader, subfolders
from endoflow.errors import DataFormatError

SPLITS = ("train", "val")
HFOV_DEG = 60.0
VFOV_DEG = 45.0


def scenenet_intrinsics(height: int, width: int) -> np.ndarray:
    """3x3 pixel K (pixel centres at integers) of SceneNet's 60 x 45 degree camera at ``height x width``."""
    fx = (width / 2) / math.tan(math.radians(HFOV_DEG / 2))
    fy = (height / 2) / math.tan(math.radians(VFOV_DEG / 2))
    return np.array([[fx, 0.0, width / 2 - 0.5], [0.0, fy, height / 2 - 0.5], [0.0, 0.0, 1.0]])


class SceneNetReader(DatasetReader):
    """Trajectories of a SceneNet RGB-D root as depth-only (optionally RGB) sequences without poses."""

    name = "scenenet"

    def __init__(self, root: str | Path, cfg: SceneNetConfig) -> None:
        super().__init__(root)
        self.cfg = cfg

    def sequences(self) -> list[Sequence]:
        splits = [self.root / split for split in SPLITS if (self.root / split).is_dir()]
        if not splits:
            raise DataFormatError(self.root, "no SceneNet split folder found (expected train/ or val/)")
        sequences = [
            self._read_trajectory(trajectory)
            for split in splits
            for part in subfolders(split)
            for trajectory in subfolders(part)
        ]
        if not sequences:
            raise DataFormatError(
                self.root, "no SceneNet trajectory found (expected <split>/<part>/<trajectory>/depth/)"
            )
        return sorted(sequences, key=lambda s: natural_key(s.name))

    def _read_trajectory(self, trajectory: Path) -> Sequence:
        part, split = trajectory.parent, trajectory.parent.parent
        depth_folder = trajectory / "depth"
        if not depth_folder.is_dir():
            raise DataFormatError(depth_folder, "depth folder not found (expected depth/<n>.png)")
        depths = numbered_files(depth_folder, r"(\d+)\.png")
        if not depths:
            raise DataFormatError(depth_folder, "empty sequence: no <n>.png depth maps")
        frame_ids = list(depths)[: self.cfg.max_frames_per_trajectory]
        depth_paths = [depths[n] for n in frame_ids]
        size = image_size(depth_paths[0])
        K = scenenet_intrinsics(*size)
        photos = _matching_photos(trajectory / "photo", frame_ids)
        return Sequence(
            dataset=self.name,
            name=f"{split.name}/{part.name}/{trajectory.name}",
            split=split.name,
            K=K,
            image_size=size,
            frame_ids=frame_ids,
            poses=None,
            load_rgb=None if photos is None else sized_loader(photos, size, read_rgb),
            load_depth=_depth_loader(depth_paths, size, K),
            group=part.name,
            source_files=[(path,) for path in depth_paths] if photos is None else list(zip(depth_paths, photos)),
        )


def _depth_loader(paths: list[Path], size: tuple[int, int], K: np.ndarray):
    """``i -> H x W`` float32 z-depth in cm from a ray-length PNG in mm."""
    to_z_cm = ray_length_to_z_factor(K, *size) / np.float32(10.0)

    def load(i: int) -> np.ndarray:
        return checked_size(paths[i], read_gray16(paths[i]), size).astype(np.float32) * to_z_cm

    return load


def _matching_photos(folder: Path, frame_ids: list[int]) -> Optional[list[Path]]:
    if not folder.is_dir():
        return None
    photos = numbered_files(folder, r"(\d+)\.jpg")
    for number in frame_ids:
        if number not in photos:
            raise DataFormatError(folder / f"{number}.jpg", f"missing image: photo for depth/{number}.png not found")
    return [photos[n] for n in frame_ids]

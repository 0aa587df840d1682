"""SimCol3D reader: the challenge's own layout, converted to the common convention of :mod:`endoflow.data.base`.

Decodes the 16-bit frames and depth maps, reads ``cam.txt`` literally and converts Unity's left-handed poses.
See docs/datasets.md, "SimCol3D".
"""

from __future__ import annotations

from pathlib import Path
import numpy as np

from endoflow.config import SimColConfig
from endoflow.data.base import DatasetReader, Sequence
from endoflow.data.imageio import image_size, read_gray16, read_rgb
from endoflow.data.layout import (
    checked_intrinsics,
    natural_key,
    numbered_files,
    pose_matrices,
    report_frame_gaps,
    report_non_finite_rows,
    sized_loader,
)
from endoflow.errors import DataFormatError
from endoflow.geometry.camera import scale_intrinsics
from endoflow.geometry.pose import unity_to_opencv

SCENES = ("SyntheticColon_I", "SyntheticColon_II", "SyntheticColon_III")
DEPTH_COUNTS_PER_CM = 255.0 * 256.0 / 20.0  # depth cm = value / 255 / 256 * 20
DEPTH_CM_PER_COUNT = 1.0 / DEPTH_COUNTS_PER_CM
FRAME_PATTERN = r"FrameBuffer_(\d+)\.png"
DEPTH_PATTERN = r"Depth_(\d+)\.png"


class SimColReader(DatasetReader):
    """Sequences of a SimCol3D root (any subset of the three scene folders)."""

    name = "simcol"

    def __init__(self, root: str | Path, cfg: SimColConfig) -> None:
        super().__init__(root)
        self.cfg = cfg

    def sequences(self) -> list[Sequence]:
        scenes = [self.root / scene for scene in SCENES if (self.root / scene).is_dir()]
        if not scenes:
            raise DataFormatError(self.root, f"no SimCol3D scene folder found (expected one of {', '.join(SCENES)})")
        found: dict[str, Sequence] = {}
        for scene in scenes:
            frame_folders = sorted(
                (p for p in scene.glob("Frames_*") if p.is_dir()), key=lambda p: natural_key(p.name)
            )
            for folder in frame_folders:
                sequence = self._read_sequence(scene, folder)
                if sequence.name in found:
                    other = found[sequence.name].group
                    raise DataFormatError(folder, f"sequence {sequence.name} also exists in {other}")
                found[sequence.name] = sequence
        return sorted(found.values(), key=lambda s: natural_key(s.name))

    def _read_sequence(self, scene: Path, folder: Path) -> Sequence:
        name = folder.name[len("Frames_") :]
        frames = numbered_files(folder, FRAME_PATTERN)
        if not frames:
            raise DataFormatError(folder, "empty sequence: no FrameBuffer_NNNN.png frames")
        depths = _matching_depths(folder, frames)
        frame_ids = list(frames)
        size = image_size(frames[frame_ids[0]])
        depth_size = image_size(depths[0])
        if depth_size != size:
            raise DataFormatError(depths[0], f"depth size {depth_size} differs from the frames' {size}")
        problems: list[str] = []
        report_frame_gaps(problems, folder, name, frame_ids)
        poses = self._read_poses(scene, name, frame_ids, problems)
        frame_paths = [frames[i] for i in frame_ids]
        return Sequence(
            dataset=self.name,
            name=name,
            split=self._split(name),
            K=self._intrinsics(scene, size),
            image_size=size,
            frame_ids=frame_ids,
            poses=poses,
            load_rgb=sized_loader(frame_paths, size, read_rgb),
            load_depth=sized_loader(depths, size, decode_depth),
            group=scene.name,
            problems=problems,
            source_files=list(zip(frame_paths, depths)),
        )

    def _split(self, name: str) -> str:
        if name in self.cfg.test:
            return "test"
        if name in self.cfg.val:
            return "val"
        return "train"

    def _intrinsics(self, scene: Path, size: tuple[int, int]) -> np.ndarray:
        if self.cfg.intrinsics is not None:
            K = checked_intrinsics(self.cfg.intrinsics, "data.simcol.intrinsics")
        else:
            K = read_cam_txt(scene / "cam.txt")
        height, width = size
        reference = float(self.cfg.reference_size)
        return scale_intrinsics(K, width / reference, height / reference)

    def _read_poses(self, scene: Path, name: str, frame_ids: list[int], problems: list[str]) -> np.ndarray:
        position_file = scene / f"SavedPosition_{name}.txt"
        rotation_file = scene / f"SavedRotationQuaternion_{name}.txt"
        positions = read_number_rows(position_file, 3)
        quaternions = read_number_rows(rotation_file, 4)
        needed = frame_ids[-1] + 1
        for path, rows in ((position_file, positions), (rotation_file, quaternions)):
            if len(rows) < needed:
                raise DataFormatError(
                    path,
                    f"pose file too short: {len(rows)} lines for {len(frame_ids)} frames "
                    f"(frame numbers up to {frame_ids[-1]} need {needed} lines)",
                )
            if len(rows) > needed:
                problems.append(f"{path.name}: {len(rows)} lines for {needed} frames; extra lines ignored")
        ids = np.asarray(frame_ids)
        zero = np.flatnonzero(np.linalg.norm(quaternions[ids], axis=1) == 0)
        if zero.size:
            raise DataFormatError(rotation_file, f"zero quaternion on line {ids[zero[0]] + 1}")
        report_non_finite_rows(problems, position_file, positions[ids], frame_ids)
        report_non_finite_rows(problems, rotation_file, quaternions[ids], frame_ids)
        return unity_to_opencv(pose_matrices(positions[ids], quaternions[ids]))


def decode_depth(path: Path) -> np.ndarray:
    """SimCol3D depth PNG -> ``H x W`` float32 z-depth in cm (``value / 255 / 256 * 20``)."""
    return read_gray16(path).astype(np.float32) * np.float32(DEPTH_CM_PER_COUNT)


def read_cam_txt(path: Path) -> np.ndarray:
    """cam.txt as the official code reads it: 9 numbers, row-major 3x3, at the reference size."""
    if not path.is_file():
        raise DataFormatError(path, "cam.txt not found (or set data.simcol.intrinsics)")
    return parse_cam_txt(path.read_text(), path)


def parse_cam_txt(text: str, source: str | Path) -> np.ndarray:
    """The 3x3 K in the text of a ``cam.txt`` (9 numbers, row-major); errors name ``source``."""
    try:
        values = [float(token) for token in text.split()]
    except ValueError:
        values = []
    if len(values) != 9:
        raise DataFormatError(source, f"malformed cam.txt: expected 9 numbers (row-major 3x3 K), found {text!r}")
    return checked_intrinsics(np.reshape(values, (3, 3)), source)


def read_number_rows(path: Path, columns: int) -> np.ndarray:
    """Whitespace-separated numbers, ``columns`` per line, as ``N x columns`` float64.

    Raises:
        DataFormatError: missing file, an empty line before the end, or a line with the wrong count.
    """
    if not path.is_file():
        raise DataFormatError(path, "pose file not found (SimCol3D keeps it in the scene folder beside Frames_*)")
    rows = []
    for number, line in enumerate(path.read_text().rstrip().splitlines(), start=1):
        try:
            values = [float(token) for token in line.split()]
        except ValueError:
            values = []
        if len(values) != columns:
            raise DataFormatError(path, f"line {number}: expected {columns} numbers, found {line!r}")
        rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, columns)


def _matching_depths(folder: Path, frames: dict[int, Path]) -> list[Path]:
    depths = numbered_files(folder, DEPTH_PATTERN)
    matched = []
    for number, frame in frames.items():
        depth = folder / frame.name.replace("FrameBuffer_", "Depth_")
        if depths.get(number) != depth:
            raise DataFormatError(depth, f"missing image: depth map for {frame.name} not found")
        matched.append(depth)
    return matched

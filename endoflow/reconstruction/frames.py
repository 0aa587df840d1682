"""Frames to reconstruct from, streamed one at a time, and the intrinsics that belong to them.

Three kinds of input: a video file (decoded with PyAV, frame by frame: a long video needs no more memory than
a short one), a folder of images (sorted by name), or a sequence of a dataset our readers know (then ground-truth
depth and poses come along). ``K`` is always in pixels of the input's native frames; the model's crop and resize
(:func:`endoflow.data.frame_encoding.stored_intrinsics`) are applied later, as preprocessing applies them for training.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import numpy as np
import yaml

from endoflow.config import Params
from endoflow.data.base import Sequence
from endoflow.data.imageio import read_rgb
from endoflow.data.registry import open_reader
from endoflow.data.simcol import parse_cam_txt
from endoflow.errors import DataFormatError

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
DEFAULT_FOLDER_FPS = 30.0  # timestamps of a folder of images: its frames are taken as 1/30 s apart


@dataclass(frozen=True)
class InputFrame:
    """One frame of the input: ``index`` its position in the whole input (before ``start``/``stride``),
    ``timestamp`` in seconds, ``rgb`` ``H x W x 3`` uint8 at the native size; ground truth where the input has it
    (``depth_cm`` z-depth in cm, ``T_world_cam`` camera-to-world in cm), else None."""

    index: int
    timestamp: float
    rgb: np.ndarray
    depth_cm: Optional[np.ndarray] = None
    T_world_cam: Optional[np.ndarray] = None


@dataclass(frozen=True)
class FrameRange:
    """Which frames of the input to use: positions ``start, start + stride, ...`` below ``stop`` (None: all)."""

    start: int = 0
    stop: Optional[int] = None
    stride: int = 1

    def __post_init__(self) -> None:
        if self.start < 0 or self.stride < 1 or (self.stop is not None and self.stop <= self.start):
            raise ValueError(f"frame range needs 0 <= start < stop and stride >= 1, got start={self.start}, "
                             f"stop={self.stop}, stride={self.stride}")

    def selects(self, index: int) -> bool:
        return index >= self.start and (index - self.start) % self.stride == 0 and not self.past(index)

    def past(self, index: int) -> bool:
        return self.stop is not None and index >= self.stop


class FrameSource:
    """A streamed input: ``frames(selection)`` yields :class:`InputFrame` in temporal order; ``location`` is the
    file or folder it reads; ``native_size`` is ``(height, width)``; ``K`` the intrinsics the input itself carries
    (a dataset's), else None; ``length`` its number of frames where known (a video's container may not say);
    ``fps`` its frame rate."""

    description: str
    location: Path
    native_size: tuple[int, int]
    K: Optional[np.ndarray] = None
    length: Optional[int] = None
    fps: float = DEFAULT_FOLDER_FPS

    def frames(self, selection: FrameRange) -> Iterator[InputFrame]:
        raise NotImplementedError


class VideoFrames(FrameSource):
    """A video file decoded with PyAV; timestamps from the stream's presentation times."""

    def __init__(self, path: Path) -> None:
        import av  # only video input needs it

        self.path = self.location = path
        try:
            with av.open(str(path)) as container:
                if not container.streams.video:
                    raise DataFormatError(path, "holds no video stream")
                stream = container.streams.video[0]
                self.native_size = (stream.codec_context.height, stream.codec_context.width)
                self.length = stream.frames or None
                self.fps = float(stream.average_rate or DEFAULT_FOLDER_FPS)
        except av.FFmpegError as exc:
            raise DataFormatError(path, f"cannot be read as a video ({exc}); expected an mp4, avi or mov file "
                                        f"that ffmpeg decodes") from None
        self.description = f"video {path}"

    def frames(self, selection: FrameRange) -> Iterator[InputFrame]:
        import av

        try:
            with av.open(str(self.path)) as container:
                stream = container.streams.video[0]
                rate = float(stream.average_rate or DEFAULT_FOLDER_FPS)
                for index, frame in enumerate(container.decode(stream)):
                    if selection.past(index):
                        return
                    if selection.selects(index):
                        seconds = float(frame.pts * stream.time_base) if frame.pts is not None else index / rate
                        yield InputFrame(index, seconds, frame.to_ndarray(format="rgb24"))
        except av.FFmpegError as exc:
            raise DataFormatError(self.path, f"video decoding failed ({exc})") from None


class FolderFrames(FrameSource):
    """Images in a folder, in natural name order (``frame_2`` before ``frame_10``), one every 1/``fps`` s."""

    def __init__(self, folder: Path, fps: float = DEFAULT_FOLDER_FPS) -> None:
        self.location = folder
        self.files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
                            key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)])
        if not self.files:
            raise DataFormatError(folder, f"no images found (expected files ending in {', '.join(IMAGE_SUFFIXES)})")
        self.fps = fps
        self.length = len(self.files)
        self.native_size = read_rgb(self.files[0]).shape[:2]
        self.description = f"{len(self.files)} images in {folder}"

    def frames(self, selection: FrameRange) -> Iterator[InputFrame]:
        for index, path in enumerate(self.files):
            if selection.past(index):
                return
            if selection.selects(index):
                rgb = read_rgb(path)
                if rgb.shape[:2] != self.native_size:
                    raise DataFormatError(path, f"image of {rgb.shape[1]}x{rgb.shape[0]} px, expected "
                                                f"{self.native_size[1]}x{self.native_size[0]} as the first image")
                yield InputFrame(index, index / self.fps, rgb)


class DatasetFrames(FrameSource):
    """A sequence of a dataset read through our readers, with its K, ground-truth depth and poses."""

    def __init__(self, root: Path, sequence: str, params: Params) -> None:
        self.location = root
        sequences = open_reader(root, None, params).sequences()
        found = [s for s in sequences if s.name == sequence]
        if not found:
            names = ", ".join(s.name for s in sequences[:12])
            raise DataFormatError(root, f"no sequence {sequence!r}; it has {len(sequences)}: {names}"
                                        f"{' ...' if len(sequences) > 12 else ''}")
        self.sequence: Sequence = found[0]
        if self.sequence.load_rgb is None:
            raise DataFormatError(root, f"sequence {sequence!r} has depth maps only, no images")
        self.native_size = tuple(self.sequence.image_size)
        self.length = len(self.sequence)
        self.K = np.asarray(self.sequence.K, dtype=np.float64)
        self.description = f"{self.sequence.dataset} sequence {sequence} of {root}"

    def frames(self, selection: FrameRange) -> Iterator[InputFrame]:
        for index in range(len(self.sequence)):
            if selection.past(index):
                return
            if selection.selects(index):
                frame = self.sequence.frame(index)
                yield InputFrame(index, index / DEFAULT_FOLDER_FPS, frame.rgb, frame.depth_cm, frame.T_world_cam)


def open_frames(source: Path, sequence: Optional[str], params: Params) -> FrameSource:
    """The frame source for ``source``: a dataset root when ``sequence`` is given, else a video file or a folder
    of images. Errors say what to provide."""
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such video, image folder or dataset root")
    if sequence is not None:
        return DatasetFrames(source, sequence, params)
    if source.is_dir():
        return FolderFrames(source)
    if source.suffix.lower() in VIDEO_SUFFIXES:
        return VideoFrames(source)
    raise DataFormatError(source, f"is neither a folder of images nor a video ({', '.join(VIDEO_SUFFIXES)}); "
                                  f"for a dataset root, also give --sequence")


# ------------------------------------------------------------------------------------------- intrinsics
def intrinsics_for(spec: Optional[str], frames: FrameSource) -> np.ndarray:
    """``3 x 3`` K in pixels of ``frames``' native size, from ``spec``: a file (SimCol ``cam.txt``: K at the
    frames' size; YAML or JSON with ``fx, fy, cx, cy, width, height``), ``"fx,fy,cx,cy"`` in pixels of the
    frames, or None for the input's own K (a dataset sequence)."""
    if spec is None:
        if frames.K is None:
            raise DataFormatError(frames.description, "no intrinsics: pass --intrinsics with a cam.txt, a YAML/JSON "
                                                      "file (fx, fy, cx, cy, width, height) or fx,fy,cx,cy in "
                                                      "pixels of the input frames")
        return frames.K
    path = Path(spec)
    if path.is_file():
        K = _intrinsics_file(path, frames.native_size)
        source = str(path)
    else:
        K = _intrinsics_numbers(spec)
        source = f"--intrinsics {spec}"
    _check_intrinsics(K, frames.native_size, source)
    return K


def _intrinsics_numbers(spec: str) -> np.ndarray:
    try:
        fx, fy, cx, cy = (float(v) for v in spec.split(","))
    except ValueError:
        raise DataFormatError(spec, "expected an intrinsics file or four numbers fx,fy,cx,cy (pixels)") from None
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _intrinsics_file(path: Path, native_size: tuple[int, int]) -> np.ndarray:
    if path.suffix.lower() == ".txt":
        return parse_cam_txt(path.read_text(), path)
    try:
        raw = json.loads(path.read_text()) if path.suffix.lower() == ".json" else yaml.safe_load(path.read_text())
        fx, fy, cx, cy = (float(raw[k]) for k in ("fx", "fy", "cx", "cy"))
        width, height = int(raw["width"]), int(raw["height"])
    except (ValueError, TypeError, KeyError, yaml.YAMLError) as exc:
        raise DataFormatError(path, f"expected fx, fy, cx, cy (pixels) and the width and height they belong to "
                                    f"({type(exc).__name__}: {exc})") from None
    if (height, width) != tuple(native_size):
        raise DataFormatError(path, f"intrinsics for {width}x{height} px, but the frames are "
                                    f"{native_size[1]}x{native_size[0]}: give intrinsics for the frames' size")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _check_intrinsics(K: np.ndarray, native_size: tuple[int, int], source: str) -> None:
    height, width = native_size
    if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and 0 < K[0, 2] < width and 0 < K[1, 2] < height):
        raise DataFormatError(source, f"intrinsics fx={K[0, 0]:g}, fy={K[1, 1]:g}, cx={K[0, 2]:g}, cy={K[1, 2]:g} "
                                      f"do not fit {width}x{height} px frames (focal lengths > 0, principal point "
                                      f"inside the image)")

"""Frames to reconstruct from, streamed one at a time, and the intrinsics that belong to them.

Three kinds of input: a video file (decoded with PyAV, frame by frame: a long video needs no more memory than
a short one), a folder of images (sorted by name), or a sequence of a dataset our readers know (then ground-truth
depth and poses come along). ``K`` is always in pixels of the input's native frames; the model's crop and resize
(:func:`endoflow.data.frame_encoding.stored_intrinsics`) are applied later, as preprocessing applies them for training.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np

from endoflow.config import Params
from endoflow.data.base import Sequence
from endoflow.data.crop import Crop, crop_image
from endoflow.data.imageio import read_rgb
from endoflow.data.intrinsics import check_intrinsics, read_intrinsics
from endoflow.data.registry import open_reader
from endoflow.data.video import DEFAULT_FOLDER_FPS, IMAGE_SUFFIXES, VIDEO_SUFFIXES, image_files
from endoflow.errors import DataFormatError


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

    def cropped(self, region: Crop) -> "InputFrame":
        """The frame (colour and ground-truth depth) cut to ``region``."""
        depth = crop_image(self.depth_cm, region) if self.depth_cm is not None else None
        return replace(self, rgb=crop_image(self.rgb, region), depth_cm=depth)


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
    ``fps`` its frame rate. ``readers(selection)`` yields, in the same order, one call per frame that returns it:
    a source whose frames decode independently (a folder, a dataset) leaves the decoding to the call, so that
    frames may decode side by side (:func:`endoflow.reconstruction.streams.decoded_ahead`); any other decodes as
    it goes, and its calls hand back what it decoded."""

    description: str
    location: Path
    native_size: tuple[int, int]
    K: Optional[np.ndarray] = None
    length: Optional[int] = None
    fps: float = DEFAULT_FOLDER_FPS

    def frames(self, selection: FrameRange) -> Iterator[InputFrame]:
        raise NotImplementedError

    def readers(self, selection: FrameRange) -> Iterator[Callable[[], InputFrame]]:
        for frame in self.frames(selection):
            yield partial(_decoded, frame)


def _decoded(frame: InputFrame) -> InputFrame:
    return frame


class IndependentFrames(FrameSource):
    """A source whose frames decode one by one, in any order and from several threads at once (image files; a video's
    frames through its :class:`~endoflow.data.video.VideoFile`, which takes one thread at a time): ``readers`` is
    its own, ``frames`` calls them."""

    def frames(self, selection: FrameRange) -> Iterator[InputFrame]:
        for read in self.readers(selection):
            yield read()

    def readers(self, selection: FrameRange) -> Iterator[Callable[[], InputFrame]]:
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
                decoded = 0
                for index, frame in enumerate(container.decode(stream)):
                    if selection.past(index):
                        return
                    decoded = index + 1
                    if selection.selects(index):
                        seconds = float(frame.pts * stream.time_base) if frame.pts is not None else index / rate
                        yield InputFrame(index, seconds, frame.to_ndarray(format="rgb24"))
        except av.FFmpegError as exc:
            raise DataFormatError(self.path, f"video decoding failed ({exc})") from None
        if self.length is not None and decoded < self.length:  # a truncated file can end without a decoding error
            raise DataFormatError(self.path, f"decoding ended after {decoded} of the {self.length} frames the video "
                                             f"declares: the file is truncated or damaged (--stop {decoded} uses "
                                             f"the frames before that point)")


class FolderFrames(IndependentFrames):
    """Images in a folder, in natural name order (``frame_2`` before ``frame_10``), one every 1/``fps`` s: those
    whose names match ``pattern`` (a glob such as ``*_color.png``), or every image when it is None, refusing
    images of different kinds (:func:`endoflow.data.video.image_files`)."""

    def __init__(self, folder: Path, fps: float = DEFAULT_FOLDER_FPS, pattern: Optional[str] = None) -> None:
        self.location = folder
        self.files = image_files(folder, pattern)
        self.fps = fps
        self.length = len(self.files)
        self.native_size = read_rgb(self.files[0]).shape[:2]
        self.description = f"{len(self.files)} images in {folder}"

    def readers(self, selection: FrameRange) -> Iterator[Callable[[], InputFrame]]:
        for index, path in enumerate(self.files):
            if selection.past(index):
                return
            if selection.selects(index):
                yield partial(self._read, index, path)

    def _read(self, index: int, path: Path) -> InputFrame:
        rgb = read_rgb(path)
        if rgb.shape[:2] != self.native_size:
            raise DataFormatError(path, f"image of {rgb.shape[1]}x{rgb.shape[0]} px, expected "
                                        f"{self.native_size[1]}x{self.native_size[0]} as the first image")
        return InputFrame(index, index / self.fps, rgb)


class DatasetFrames(IndependentFrames):
    """A sequence of a dataset read through our readers, with its K, ground-truth depth and poses."""

    def __init__(self, root: Path, sequence: str, params: Params) -> None:
        self.location = root
        sequences = open_reader(root, None, params).sequences()
        found = [s for s in sequences if s.name == sequence]
        if not found:
            raise DataFormatError(root, f"no sequence {sequence!r}; it has {sequence_names(sequences)}")
        self.sequence: Sequence = found[0]
        if self.sequence.load_rgb is None:
            raise DataFormatError(root, f"sequence {sequence!r} has depth maps only, no images")
        self.native_size = tuple(self.sequence.image_size)
        self.length = len(self.sequence)
        self.K = np.asarray(self.sequence.K, dtype=np.float64)
        self.description = f"{self.sequence.dataset} sequence {sequence} of {root}"

    def readers(self, selection: FrameRange) -> Iterator[Callable[[], InputFrame]]:
        for index in range(len(self.sequence)):
            if selection.past(index):
                return
            if selection.selects(index):
                yield partial(self._read, index)

    def _read(self, index: int) -> InputFrame:
        frame = self.sequence.frame(index)
        return InputFrame(index, index / DEFAULT_FOLDER_FPS, frame.rgb, frame.depth_cm, frame.T_world_cam)


def sequence_names(sequences: list[Sequence], shown: int = 12) -> str:
    """``"3: B1, O1, S1"``: how many sequences, and the first ``shown`` names."""
    names = ", ".join(s.name for s in sequences[:shown])
    return f"{len(sequences)}: {names}{' ...' if len(sequences) > shown else ''}"


def open_frames(source: Path, sequence: Optional[str], params: Params, pattern: Optional[str] = None) -> FrameSource:
    """The frame source for ``source``: a dataset root when ``sequence`` is given, else a video file or a folder
    of images (those matching the glob ``pattern``, see :class:`FolderFrames`). Errors say what to provide."""
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such video, image folder or dataset root")
    if pattern is not None and (sequence is not None or not source.is_dir()):
        raise DataFormatError(source, f"--pattern {pattern!r} picks images of a folder; this input is not one")
    if sequence is not None:
        return DatasetFrames(source, sequence, params)
    if source.is_dir():
        if not any(p.suffix.lower() in IMAGE_SUFFIXES for p in source.iterdir()):
            refuse_dataset_root(source, params)
        return FolderFrames(source, pattern=pattern)
    if source.suffix.lower() in VIDEO_SUFFIXES:
        return VideoFrames(source)
    raise DataFormatError(source, f"is neither a folder of images nor a video ({', '.join(VIDEO_SUFFIXES)}); "
                                  f"for a dataset root, also give --sequence")


def refuse_dataset_root(folder: Path, params: Params) -> None:
    """Raise, listing its sequences, if ``folder`` (which holds no images) is a dataset root our readers know:
    it needs ``--sequence``."""
    try:
        reader = open_reader(folder, None, params)
        sequences = reader.sequences()
    except DataFormatError:  # not a dataset root either: the folder's own error says what was expected
        return
    raise DataFormatError(folder, f"is a {reader.name} dataset root: pick a sequence with --sequence (it has "
                                  f"{sequence_names(sequences)})")


# ------------------------------------------------------------------------------------------- intrinsics
def intrinsics_for(spec: Optional[str], frames: FrameSource, crop: Optional[Crop] = None) -> Optional[np.ndarray]:
    """``3 x 3`` K in pixels of ``frames``' native size, from ``spec``: a file (SimCol ``cam.txt``: K at the
    frames' size; YAML or JSON with ``fx, fy, cx, cy, width, height``), ``"fx,fy,cx,cy"`` in pixels of the
    frames, or None for the input's own K (a dataset sequence); None where neither gives one (a video nobody
    calibrated: :func:`~endoflow.reconstruction.reconstruct.input_intrinsics` takes over). Checked
    (:func:`check_intrinsics`) against the frames and the part of them the model sees (``crop``, see
    :mod:`endoflow.data.crop`)."""
    if spec is None:
        if frames.K is None:
            return None
        K, source = frames.K, f"the intrinsics of {frames.description}"
    else:
        K = read_intrinsics(spec, frames.native_size)
        source = spec if Path(spec).is_file() else f"--intrinsics {spec}"
    check_intrinsics(K, frames.native_size, source, crop)
    return K

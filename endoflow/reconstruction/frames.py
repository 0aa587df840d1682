"""Frames to reconstruct from, streamed one at a time, and the intrinsics that belong to them.

Three kinds of input: a video file (decoded with PyAV, frame by frame: a long video needs no more memory than
a short one), a folder of images (sorted by name), or a sequence of a dataset our readers know (then ground-truth
depth and poses come along). ``K`` is always in pixels of the input's native frames; the model's crop and resize
(:func:`endoflow.data.frame_encoding.stored_intrinsics`) are applied later, as preprocessing applies them for training.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, replace
from fnmatch import fnmatch
from pathlib import Path
from typing import Iterator, Optional

import cv2
import numpy as np
import yaml

from endoflow.config import Params
from endoflow.data.base import Sequence
from endoflow.data.imageio import read_rgb
from endoflow.data.registry import open_reader
from endoflow.data.simcol import parse_cam_txt
from endoflow.errors import DataFormatError
from endoflow.reconstruction.crop import Crop, crop_image, frame_region, model_view

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
DEFAULT_FOLDER_FPS = 30.0  # timestamps of a folder of images: its frames are taken as 1/30 s apart
# Plausible field of view of a frame, each axis, degrees: a pinhole camera's is below 180 and endoscopes reach about
# 170; focal lengths outside (fx = 1 px, or 1e9 px) are in other units or of another image size.
FIELD_OF_VIEW_DEG = (10.0, 170.0)


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


class FolderFrames(FrameSource):
    """Images in a folder, in natural name order (``frame_2`` before ``frame_10``), one every 1/``fps`` s: those
    whose names match ``pattern`` (a glob such as ``*_color.png``), or every image when it is None, refusing
    images of different kinds (:func:`refuse_mixed_images`)."""

    def __init__(self, folder: Path, fps: float = DEFAULT_FOLDER_FPS, pattern: Optional[str] = None) -> None:
        self.location = folder
        images = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=natural_order)
        self.files = [p for p in images if pattern is None or fnmatch(p.name, pattern)]
        if not self.files and pattern is not None and images:
            raise DataFormatError(folder, f"no image matches --pattern {pattern!r}; it holds {len(images)} images, "
                                          f"such as {', '.join(p.name for p in images[:3])}")
        if not self.files:
            raise DataFormatError(folder, f"no images found (expected files ending in {', '.join(IMAGE_SUFFIXES)})")
        if pattern is None:
            refuse_mixed_images(folder, self.files)
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


def natural_order(path: Path) -> list:
    """Sort key: digit runs compare as numbers (``frame_2`` before ``frame_10``)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def refuse_mixed_images(folder: Path, files: list[Path]) -> None:
    """Raise when ``files`` are images of more than one kind (size, channels, bit depth): frames mixed with depth
    maps or masks, as in C3VD's sequence folders. Each naming scheme (the name with its digits left out, so
    ``0_color.png`` and ``30_color.png`` share one) is judged on its first file; the error lists each kind with an
    example and suggests a ``--pattern`` for the colour ones."""
    schemes: dict[str, list[Path]] = {}
    for path in files:
        schemes.setdefault(re.sub(r"\d+", "*", path.name), []).append(path)
    kinds = {scheme: image_kind(members[0]) for scheme, members in schemes.items()}
    if len(set(kinds.values())) < 2:
        return
    listing = "; ".join(f"{len(schemes[s])} like {schemes[s][0].name} ({describe_kind(kinds[s])})" for s in schemes)
    colour = " or ".join(f"--pattern '{s}'" for s in schemes if kinds[s] is not None and kinds[s][2] in (3, 4))
    raise DataFormatError(folder, f"holds images of different kinds, frames mixed with other files: {listing}; "
                                  f"pick the frames with --pattern GLOB{f' ({colour})' if colour else ''}")


def image_kind(path: Path) -> Optional[tuple[int, int, int, int]]:
    """``(width, height, channels, bits per sample)`` of an image file; None if it does not decode."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    channels = 1 if image.ndim == 2 else image.shape[2]
    return image.shape[1], image.shape[0], channels, image.dtype.itemsize * 8


def describe_kind(kind: Optional[tuple[int, int, int, int]]) -> str:
    if kind is None:
        return "not a decodable image"
    width, height, channels, bits = kind
    return f"{width}x{height} px, {channels} channel{'s' if channels > 1 else ''}, {bits}-bit"


class DatasetFrames(FrameSource):
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

    def frames(self, selection: FrameRange) -> Iterator[InputFrame]:
        for index in range(len(self.sequence)):
            if selection.past(index):
                return
            if selection.selects(index):
                frame = self.sequence.frame(index)
                yield InputFrame(index, index / DEFAULT_FOLDER_FPS, frame.rgb, frame.depth_cm, frame.T_world_cam)


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
def intrinsics_for(spec: Optional[str], frames: FrameSource, crop: Optional[Crop] = None) -> np.ndarray:
    """``3 x 3`` K in pixels of ``frames``' native size, from ``spec``: a file (SimCol ``cam.txt``: K at the
    frames' size; YAML or JSON with ``fx, fy, cx, cy, width, height``), ``"fx,fy,cx,cy"`` in pixels of the
    frames, or None for the input's own K (a dataset sequence). Checked (:func:`check_intrinsics`) against the
    frames and the part of them the model sees (``crop``, see :mod:`endoflow.reconstruction.crop`)."""
    if spec is None:
        if frames.K is None:
            raise DataFormatError(frames.description, "no intrinsics: pass --intrinsics with a cam.txt, a YAML/JSON "
                                                      "file (fx, fy, cx, cy, width, height) or fx,fy,cx,cy in "
                                                      "pixels of the input frames")
        K, source = frames.K, f"the intrinsics of {frames.description}"
    elif Path(spec).is_file():
        K, source = _intrinsics_file(Path(spec), frames.native_size), spec
    else:
        K, source = _intrinsics_numbers(spec), f"--intrinsics {spec}"
    check_intrinsics(K, frames.native_size, source, crop)
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


def check_intrinsics(K: np.ndarray, native_size: tuple[int, int], source: str, crop: Optional[Crop] = None) -> None:
    """Refuse, naming ``source``, a K that cannot be the frames' (non-finite, a focal length <= 0, the principal
    point outside the image), whose field of view is implausible (:data:`FIELD_OF_VIEW_DEG`: focal lengths in
    other units or of another image size), or whose principal point lies outside the square the model sees."""
    height, width = native_size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (np.isfinite(K).all() and fx > 0 and fy > 0 and 0 < cx < width and 0 < cy < height):
        raise DataFormatError(source, f"intrinsics fx={fx:g}, fy={fy:g}, cx={cx:g}, cy={cy:g} do not fit "
                                      f"{width}x{height} px frames (focal lengths > 0, principal point inside the "
                                      f"image)")
    across = [math.degrees(2 * math.atan(extent / (2 * focal))) for extent, focal in ((width, fx), (height, fy))]
    low, high = FIELD_OF_VIEW_DEG
    if not all(low <= angle <= high for angle in across):
        raise DataFormatError(source, f"intrinsics fx={fx:g}, fy={fy:g} give the {width}x{height} px frames a field "
                                      f"of view of {across[0]:.3g} x {across[1]:.3g} degrees, outside the plausible "
                                      f"{low:g} to {high:g}: give focal lengths in pixels of these frames")
    view = model_view(frame_region(native_size, crop, source))
    if not (view.x - 0.5 <= cx <= view.x + view.width - 0.5 and view.y - 0.5 <= cy <= view.y + view.height - 0.5):
        raise DataFormatError(source, f"principal point cx={cx:g}, cy={cy:g} lies outside the square the model sees, "
                                      f"{view} (the centre square of the {'--crop region' if crop else 'frames'}): "
                                      f"these intrinsics are not of these frames, or --crop cuts the optical axis "
                                      f"away")

"""Unlabelled video as a dataset: any folder of video files and frame folders, each a sequence.

The footage a user has: an endoscope's video with no depth, no poses and often no calibration. Under the root
(``data.video.root``) every video file (:data:`VIDEO_SUFFIXES`) and every folder of images is a sequence named
after it (``clip.mp4`` and ``clip/`` are both ``clip``; having both is an error). Its intrinsics, in pixels of the
native frames and in any form :mod:`endoflow.data.intrinsics` reads, come from a sidecar file
``<name>.intrinsics.{json,yaml,yml,txt}`` beside it, else from ``data.video.intrinsics``, else they are unknown:
K is then assumed from ``data.assumed_fov_deg`` (a pinhole of that diagonal field of view, centred), and the
sequence says so (``Sequence.intrinsics_known``), as do its shards. ``data.video.crop`` cuts every frame to a
region first (one view of a side-by-side recording, a burnt-in overlay left out), ``data.video.fps`` keeps every
n-th frame for a target frame rate. Splits: sequences named in ``val`` or ``test`` go there whole; of every other
sequence the last ``val_share`` of its frames is a validation sequence of its own, ``<name>@val`` (split by time,
so one video can train and validate).

Frames are decoded on demand (:class:`VideoFile`: seeks to the key frame before a frame and decodes forward,
keeping the last few), so a long video needs no more memory than a short one and a shard writer reading frames in
order decodes each about once.
"""

from __future__ import annotations

import math
import re
import threading
from collections import OrderedDict
from dataclasses import dataclass
from fnmatch import fnmatch
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from endoflow.config import VideoConfig
from endoflow.data.base import DatasetReader, Sequence
from endoflow.data.crop import Crop, crop_image, crop_intrinsics, frame_region
from endoflow.data.imageio import read_rgb
from endoflow.data.intrinsics import assumed_intrinsics, check_intrinsics, read_intrinsics
from endoflow.data.layout import natural_key
from endoflow.errors import DataFormatError

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
INTRINSICS_SIDECARS = (".json", ".yaml", ".yml", ".txt")
DEFAULT_FOLDER_FPS = 30.0  # timestamps of a folder of images: its frames are taken as 1/30 s apart
VAL_SUFFIX = "@val"
# Decoded frames a VideoFile keeps: a triplet's three and the frames between them at wider offsets.
KEPT_FRAMES = 8
# Decoding forward is cheaper than a seek (which restarts at a key frame) up to about a group of pictures.
FORWARD_DECODE_LIMIT = 48


# ------------------------------------------------------------------------------------------------ frames
def natural_order(path: Path) -> tuple:
    """Sort key of a file by name, digit runs compared as numbers (``frame_2`` before ``frame_10``)."""
    return natural_key(path.name)


def image_files(folder: Path, pattern: Optional[str] = None) -> list[Path]:
    """The frames of a folder in natural name order: the images whose names match the glob ``pattern``, or every
    image when it is None, refusing images of different kinds (:func:`refuse_mixed_images`)."""
    images = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=natural_order)
    files = [p for p in images if pattern is None or fnmatch(p.name, pattern)]
    if not files and pattern is not None and images:
        raise DataFormatError(folder, f"no image matches --pattern {pattern!r}; it holds {len(images)} images, "
                                      f"such as {', '.join(p.name for p in images[:3])}")
    if not files:
        raise DataFormatError(folder, f"no images found (expected files ending in {', '.join(IMAGE_SUFFIXES)})")
    if pattern is None:
        refuse_mixed_images(folder, files)
    return files


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


class VideoFile:
    """A video file's frames by position (0 = the first in presentation order), decoded with PyAV on demand.

    Opening it reads the container's packets, not its pictures, to list every frame's presentation time: positions
    then map to times exactly, whatever the codec's frame reordering. A frame is found by seeking to the key
    frame before it and decoding forward; the last :data:`KEPT_FRAMES` decoded stay, so frames asked for in order
    are each decoded about once. One decoder serves one thread at a time: threads decoding a sequence's frames side
    by side (``reconstruct`` on many cores) take turns, and frames asked for a little out of order are still among
    those kept. The open container is not pickled: a copy in another process opens its own.

    Raises:
        DataFormatError: naming the file: no video stream, not decodable, or a frame that cannot be reached.
    """

    def __init__(self, path: Path) -> None:
        import av  # only video input needs it

        self.path = Path(path)
        try:
            with av.open(str(self.path)) as container:
                if not container.streams.video:
                    raise DataFormatError(self.path, "holds no video stream")
                stream = container.streams.video[0]
                self.size = (stream.codec_context.height, stream.codec_context.width)
                self.fps = float(stream.average_rate or DEFAULT_FOLDER_FPS)
                self.times = sorted(packet.pts for packet in container.demux(stream) if packet.pts is not None)
        except av.FFmpegError as exc:
            raise DataFormatError(self.path, f"cannot be read as a video ({exc}); expected an mp4, avi, mov or mkv "
                                             f"file that ffmpeg decodes") from None
        if not self.times:
            raise DataFormatError(self.path, "holds no frames")
        self._position = {time: index for index, time in enumerate(self.times)}
        self._lock = threading.Lock()
        self._reset()

    def __len__(self) -> int:
        return len(self.times)

    def __getstate__(self) -> dict:
        return {key: value for key, value in self.__dict__.items()
                if key not in ("_container", "_frames", "_kept", "_lock")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
        self._reset()

    def _reset(self) -> None:
        self._container = None
        self._frames = None  # the decoder's iterator, from where it last stopped
        self._next = None  # position of the frame it yields next
        self._kept: OrderedDict[int, np.ndarray] = OrderedDict()

    def __call__(self, index: int) -> np.ndarray:
        """``H x W x 3`` uint8 RGB of the frame at ``index``."""
        if not 0 <= index < len(self.times):
            raise IndexError(f"{self.path}: frame {index} of {len(self.times)}")
        with self._lock:
            if index not in self._kept:
                self._decode_up_to(index)
            return self._kept[index]

    def _decode_up_to(self, index: int) -> None:
        import av

        try:
            if self._next is None or not self._next <= index < self._next + FORWARD_DECODE_LIMIT:
                self._seek(index)
            while self._next <= index:
                frame = next(self._frames)
                position = self._position.get(frame.pts)
                if position is None or position < self._next:  # before the frame the seek asked for
                    continue
                self._keep(position, frame.to_ndarray(format="rgb24"))
                self._next = position + 1
        except (StopIteration, av.FFmpegError) as exc:
            self._reset()
            raise DataFormatError(self.path, f"frame {index} of the {len(self.times)} it lists cannot be decoded "
                                             f"({exc or 'the stream ends before it'}): the file is truncated or "
                                             f"damaged") from None

    def _seek(self, index: int) -> None:
        import av

        if self._container is None:
            self._container = av.open(str(self.path))
        stream = self._container.streams.video[0]
        self._container.seek(self.times[index], stream=stream, backward=True, any_frame=False)
        self._frames = self._container.decode(stream)
        self._next = index

    def _keep(self, position: int, rgb: np.ndarray) -> None:
        self._kept[position] = rgb
        while len(self._kept) > KEPT_FRAMES:
            self._kept.popitem(last=False)


@dataclass(frozen=True)
class CroppedFrames:
    """``i -> rgb``: the ``i``-th frame of a sequence, the ``frame_ids[i]``-th of ``source`` (a :class:`VideoFile`
    or the image files of a folder), cut to ``region`` (picklable, for loader processes and Ray tasks)."""

    source: object
    frame_ids: tuple[int, ...]
    region: Crop

    def __call__(self, i: int) -> np.ndarray:
        index = self.frame_ids[i]
        rgb = self.source(index) if isinstance(self.source, VideoFile) else read_rgb(self.source[index])
        return np.ascontiguousarray(crop_image(rgb, self.region))


# ------------------------------------------------------------------------------------------------ reader
@dataclass(frozen=True)
class Recording:
    """One video file or frame folder under the root: its frames, their rate and size, where it lies."""

    name: str
    location: Path
    frames: object  # a VideoFile, or the list of image files
    fps: float
    size: tuple[int, int]

    @property
    def count(self) -> int:
        return len(self.frames)


class VideoReader(DatasetReader):
    """The video dataset under ``root`` (module docstring); settings ``data.video``."""

    name = "video"

    def __init__(self, root: str | Path, cfg: VideoConfig, assumed_fov_deg: float,
                 intrinsics: Optional[str] = None) -> None:
        super().__init__(root)
        self.cfg = cfg
        self.assumed_fov_deg = assumed_fov_deg
        self.override = intrinsics  # given by the user for these frames: before a sidecar

    def sequences(self) -> list[Sequence]:
        recordings = self.recordings()
        known = {r.name for r in recordings}
        for listed in (*self.cfg.val, *self.cfg.test):
            if listed not in known:
                raise DataFormatError(self.root, f"data.video lists sequence {listed!r}, which is not here (it has "
                                                 f"{', '.join(sorted(known))})")
        sequences: list[Sequence] = []
        for recording in recordings:
            sequences.extend(self._split(recording))
        return sorted(sequences, key=lambda s: s.name)

    def recordings(self) -> list[Recording]:
        """Every video file and frame folder directly under the root, by name."""
        found: dict[str, Recording] = {}
        for path in sorted(self.root.iterdir(), key=natural_order):
            recording = read_recording(path, self.cfg.folder_fps)
            if recording is None:
                continue
            if recording.name in found:
                raise DataFormatError(path, f"names the same sequence as {found[recording.name].location}; rename "
                                            f"one of them")
            found[recording.name] = recording
        if not found:
            raise DataFormatError(self.root, f"no videos ({', '.join(VIDEO_SUFFIXES)}) or folders of images found")
        return list(found.values())

    def _split(self, recording: Recording) -> list[Sequence]:
        frame_ids = self.frame_ids(recording)
        for split, names in (("test", self.cfg.test), ("val", self.cfg.val)):
            if recording.name in names:
                return [self.sequence(recording, recording.name, split, frame_ids)]
        held_out = math.floor(len(frame_ids) * self.cfg.val_share)
        kept = len(frame_ids) - held_out
        parts = [self.sequence(recording, recording.name, "train", frame_ids[:kept])]
        if held_out:
            parts.append(self.sequence(recording, recording.name + VAL_SUFFIX, "val", frame_ids[kept:]))
        return parts

    def frame_ids(self, recording: Recording) -> list[int]:
        """The frames kept of a recording: every ``round(native / data.video.fps)``-th."""
        return list(range(0, recording.count, frame_stride(recording.fps, self.cfg.fps)))

    def sequence(self, recording: Recording, name: str, split: str, frame_ids: list[int]) -> Sequence:
        """The sequence of a recording's frames ``frame_ids``, cut to ``data.video.crop``, with its intrinsics."""
        region = self.region(recording)
        K, known = self.intrinsics(recording, region)
        files = (recording.location,) if isinstance(recording.frames, VideoFile) else None
        return Sequence(
            dataset=self.name,
            name=name,
            split=split,
            K=K,
            image_size=region.size,
            frame_ids=frame_ids,
            poses=None,
            load_rgb=CroppedFrames(recording.frames, tuple(frame_ids), region),
            load_depth=None,
            group=self.name,
            source_files=[files or (recording.frames[i],) for i in frame_ids],
            intrinsics_known=known,
        )

    def region(self, recording: Recording) -> Crop:
        crop = Crop(*self.cfg.crop) if self.cfg.crop is not None else None
        return frame_region(recording.size, crop, f"{recording.location} (data.video.crop)")

    def intrinsics(self, recording: Recording, region: Crop) -> tuple[np.ndarray, bool]:
        """K of the cropped frames, and whether it was given (a sidecar file, ``data.video.intrinsics``) rather
        than assumed (:func:`assumed_intrinsics`)."""
        sidecars = [self.root / f"{recording.name}.intrinsics{suffix}" for suffix in INTRINSICS_SIDECARS]
        spec = self.override or next((str(p) for p in sidecars if p.is_file()), self.cfg.intrinsics)
        if spec is None:
            return assumed_intrinsics(region.size, self.assumed_fov_deg), False
        K = read_intrinsics(spec, recording.size)
        check_intrinsics(K, recording.size, spec, region)
        return crop_intrinsics(K, region), True


def read_recording(path: Path, folder_fps: float, pattern: Optional[str] = None) -> Optional[Recording]:
    """``path`` as a recording: a video file, or a folder of images (those matching the glob ``pattern``, every
    image when it is None, see :func:`image_files`; one every ``1 / folder_fps`` s); None for anything else."""
    if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
        video = VideoFile(path)
        return Recording(path.stem, path, video, video.fps, video.size)
    if path.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir()):
        files = image_files(path, pattern)
        return Recording(path.name, path, files, folder_fps, read_rgb(files[0]).shape[:2])
    return None


def video_sequence(path: Path, cfg: VideoConfig, assumed_fov_deg: float, intrinsics: Optional[str] = None,
                   pattern: Optional[str] = None) -> Sequence:
    """One video file or folder of frames as one whole sequence (split ``train``), read as the video dataset reads
    its sequences (``data.video``'s crop, frame rate and intrinsics, the sidecar beside it; ``intrinsics`` first);
    ``pattern`` picks a folder's frames (:func:`image_files`)."""
    if pattern is not None and not Path(path).is_dir():
        raise DataFormatError(path, f"--pattern {pattern!r} picks images of a folder; this input is not one")
    recording = read_recording(Path(path), cfg.folder_fps, pattern)
    if recording is None:
        raise DataFormatError(path, f"is neither a video ({', '.join(VIDEO_SUFFIXES)}) nor a folder of images")
    reader = VideoReader(Path(path).parent, cfg, assumed_fov_deg, intrinsics)
    return reader.sequence(recording, recording.name, "train", reader.frame_ids(recording))


def frame_stride(native_fps: float, target_fps: Optional[float]) -> int:
    """Every how many frames one is kept for ``target_fps`` (None: every frame; never fewer than one)."""
    if target_fps is None or target_fps >= native_fps:
        return 1
    return max(1, round(native_fps / target_fps))

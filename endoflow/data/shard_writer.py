"""Writing one planned shard: its samples encoded and streamed into one tar, hashed as it is written.

A sample's files are the stored-size RGB of ``prev`` / ``cur`` / ``next`` (:mod:`endoflow.data.frame_encoding`),
the target's depth in counts of ``EncodeSettings.depth_unit`` cm (0 where unknown, where the dataset has no
depth, or beyond the encodable range ``65535 * depth_unit``) and ``meta.json`` (K at the stored size, or the assumed one where ``preprocess.withhold_intrinsics`` says so, the poses
``T_world_cam``, null where a frame has none: a non-finite value is never written as a pose); depth-only
datasets store only ``depth.png`` and ``meta.json``. Member names and decoding are
:mod:`endoflow.data.shard_format`'s. Each shard decodes and resizes a frame once even though three samples use
it, and the same samples give the same bytes on any machine and with either engine.
"""

from __future__ import annotations

import json
import posixpath
from dataclasses import dataclass
from typing import Optional

import numpy as np
import webdataset as wds

from endoflow.data.base import Sequence
from endoflow.data.field_of_view import resized_field_of_view
from endoflow.data.intrinsics import assumed_intrinsics
from endoflow.data.frame_encoding import depth_to_counts, encode_png, resize_depth, resize_rgb, stored_intrinsics
from endoflow.data.shard_format import (
    DEPTH_MEMBER,
    IMAGE_NAMES,
    META_MEMBER,
    VALID_MEMBER,
    HashingWriter,
    ShardEntry,
    sample_sha256,
)
from endoflow.data.shard_plan import EncodeSettings, SampleSpec, ShardSpec, sample_positions
from endoflow.errors import DataFormatError
from endoflow.io import atomic_location

# TarWriter streams 10 KiB tar records; a large file buffer makes them few large writes (bench_tar_writer.py).
WRITE_BUFFER = 8 << 20


@dataclass(frozen=True)
class ShardResult:
    entry: ShardEntry  # what the manifest records of the shard, hashed as it was written
    frames_decoded: int
    depth_out_of_range: int


def write_shard(
    shard: ShardSpec, staging: str, settings: EncodeSettings, sequences: dict[str, Sequence]
) -> ShardResult:
    """Encode the samples of ``shard`` and write them as one tar into ``staging`` (a path or URL), atomically.

    Members have fixed metadata (mtime 0, owner and group empty, sorted member order), so the same samples
    give identical bytes on any machine.
    """
    cache = FrameCache(settings)
    out_of_range = 0
    digests = []
    location = posixpath.join(staging, shard.name)
    with atomic_location(location) as temporary, open(temporary, "wb", buffering=WRITE_BUFFER) as stream:
        hashing = HashingWriter(stream)
        with wds.TarWriter(hashing, encoder=False, mtime=0, user="", group="") as tar:
            for spec in shard.samples:
                files, bad_depth = encode_sample(spec, sequences[spec.sequence], settings, cache)
                out_of_range += bad_depth
                tar.write({"__key__": spec.key, **files})
                digests.append((spec.key, sample_sha256(files)))
    frames = len(shard.samples) if settings.depth_only else cache.decoded
    entry = ShardEntry(shard.name, len(shard.samples), hashing.digest.hexdigest(), tuple(digests))
    return ShardResult(entry, frames, out_of_range)


class FrameCache:
    """Encoded stored-size RGB frames of the sequence being written, kept while a later sample needs them.

    Samples arrive in sequence order, so a frame is evicted once it is older than the earliest neighbour a
    later sample can ask for.
    """

    def __init__(self, settings: EncodeSettings) -> None:
        self.settings = settings
        self.sequence: Optional[str] = None
        self.frames: dict[int, bytes] = {}
        self.decoded = 0
        self.valid_of: Optional[str] = None
        self.valid = b""

    def rgb_png(self, sequence: Sequence, position: int) -> bytes:
        if sequence.name != self.sequence:
            self.sequence, self.frames = sequence.name, {}
        if position not in self.frames:
            if sequence.load_rgb is None:
                raise DataFormatError(sequence.name, f"{sequence.dataset} sequence has no RGB frames")
            rgb = sequence.load_rgb(position)
            check_frame(rgb, sequence, position, channels=3)
            self.frames[position] = encode_png(resize_rgb(rgb, self.settings.size))
            self.decoded += 1
        return self.frames[position]

    def valid_png(self, sequence: Sequence) -> bytes:
        """The sequence's field of view at the stored size, 255 in and 0 out."""
        if sequence.name != self.valid_of:
            valid = resized_field_of_view(sequence.field_of_view(), self.settings.size)
            self.valid_of, self.valid = sequence.name, encode_png(valid.astype(np.uint8) * 255)
        return self.valid

    def evict_before(self, position: int) -> None:
        for old in [p for p in self.frames if p < position]:
            del self.frames[old]


def encode_sample(
    spec: SampleSpec, sequence: Sequence, settings: EncodeSettings, cache: FrameCache
) -> tuple[dict[str, bytes], int]:
    """The files of one sample (extension -> bytes) and its count of depth pixels beyond range."""
    i = spec.position
    frames = sample_positions(spec, settings)
    positions = dict(zip(("cur",) if settings.depth_only else IMAGE_NAMES, frames))
    files: dict[str, bytes] = {}
    if not settings.depth_only:
        cache.evict_before(frames[0])
        for name, position in positions.items():
            files[f"{name}.png"] = cache.rgb_png(sequence, position)
    depth_counts, out_of_range = depth_to_counts(stored_depth(sequence, i, settings.size), settings.depth_unit)
    files[DEPTH_MEMBER] = encode_png(depth_counts)
    if not settings.depth_only:
        files[VALID_MEMBER] = cache.valid_png(sequence)
    files[META_MEMBER] = json.dumps(sample_meta(spec, sequence, positions, settings), sort_keys=True).encode()
    return files, out_of_range


def sample_meta(
    spec: SampleSpec, sequence: Sequence, positions: dict[str, int], settings: EncodeSettings
) -> dict:
    names = IMAGE_NAMES
    withheld = settings.withheld_fov_deg
    native_K = sequence.K if withheld is None else assumed_intrinsics(sequence.image_size, withheld)
    poses = {name: _pose_list(sequence, positions[name]) if name in positions else None for name in names}
    frame_ids = {name: int(sequence.frame_ids[positions[name]]) if name in positions else None for name in names}
    return {
        "dataset": settings.dataset,
        "sequence": spec.sequence,
        "group": spec.group,
        "split": spec.split,
        "frame": spec.frame,
        "frame_ids": frame_ids,
        "neighbour_offset": None if settings.depth_only else spec.offset,
        "K": stored_intrinsics(native_K, sequence.image_size, settings.size).tolist(),
        "T_world_cam": poses,
        "depth_unit": settings.depth_unit,
        "native_size": [int(sequence.image_size[0]), int(sequence.image_size[1])],
        "intrinsics_known": bool(sequence.intrinsics_known) and withheld is None,
        "ground_truth": {"depth": sequence.load_depth is not None, "pose": sequence.poses is not None},
    }


def _pose_list(sequence: Sequence, position: int) -> Optional[list[list[float]]]:
    pose = sequence.pose(position)
    return None if pose is None else np.asarray(pose, dtype=np.float64).tolist()


def stored_depth(sequence: Sequence, position: int, size: int) -> np.ndarray:
    """``size x size`` float32 z-depth in cm of a frame; zeros (unknown) when the dataset has none."""
    if sequence.load_depth is None:
        return np.zeros((size, size), np.float32)
    depth = sequence.load_depth(position)
    check_frame(depth, sequence, position, channels=None)
    return resize_depth(np.asarray(depth, dtype=np.float32), size)


def check_frame(array: np.ndarray, sequence: Sequence, position: int, channels: Optional[int]) -> None:
    """Frames must have the sequence's size (and 3 uint8 channels for colour)."""
    expected = tuple(sequence.image_size)
    if channels is None:
        ok = array.ndim == 2 and array.shape == expected
        what = f"H x W depth of size {expected}"
    else:
        ok = array.shape == (*expected, channels) and array.dtype == np.uint8
        what = f"{expected[0]} x {expected[1]} x {channels} uint8"
    if not ok:
        raise DataFormatError(
            f"{sequence.dataset}/{sequence.name}",
            f"frame {sequence.frame_ids[position]}: expected {what}, found {array.dtype} {array.shape}",
        )

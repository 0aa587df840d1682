"""The preprocessing plan: which samples a dataset gives, how they fill shards, and each shard's resume key.

Each sample is one target frame ``cur`` with its neighbours ``prev`` / ``next`` at
``-/+ preprocess.neighbour_offset`` (in the train split, with ``preprocess.train_offsets``, at each target's own
offset, taken from that list in turn); depth-only datasets (SceneNet, for the latent bank) make every frame a
sample. A target is taken only when its neighbours are the frames exactly its offset in regular frame steps away,
so no sample spans a missing frame (the reader warns about gaps). A frame without a pose (none in
the data, or NaN / inf in the pose file: the reader warns, naming the file and frames) keeps its sample, whose
images are sound; :func:`samples_without_pose` counts them for the summary.

Each split's samples, in sequence order, are spread evenly (sizes differ by at most one) over a shard count that
is a multiple of ``preprocess.shard_multiple``, so whole shards divide evenly over that many training workers.
Keys (``<dataset>-<sequence>-<frame>``) depend only on the data, never on the run. :func:`shard_keys` hashes
everything a shard is built from, so a rerun reuses a finished shard only while nothing it read changed.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from endoflow.config import Params, params_to_dict
from endoflow.data.base import DEPTH_ONLY_DATASETS, Sequence, slug
from endoflow.data.shard_format import FORMAT_VERSION, SPLITS, shard_name
from endoflow.errors import DataFormatError

# cm per stored depth count: colon data up to 65.535 cm at 10 um steps (finer than SimCol3D's own 0.078 cm);
# indoor scenes up to 65.5 m at 1 mm.
DEPTH_UNIT_CM = {"simcol": 0.001, "endoslam": 0.001, "scenenet": 0.1}


@dataclass(frozen=True)
class EncodeSettings:
    """How samples of one dataset are written (identical in every worker)."""

    dataset: str
    size: int
    neighbour_offset: int
    train_offsets: tuple[int, ...]  # the train split's offsets in turn (preprocess.train_offsets, else neighbour_offset)
    depth_unit: float
    depth_only: bool
    # data.<dataset> as JSON: reader settings (depth scale, units, intrinsics...) change the decoded frames
    # without changing any file, so they are part of every shard's resume key
    reader_params: str
    # preprocess.withhold_intrinsics: the field of view every sequence's K is assumed from instead (None: its own)
    withheld_fov_deg: Optional[float] = None


@dataclass(frozen=True)
class SampleSpec:
    """One planned sample: target frame ``position`` (index into the sequence) and its key."""

    key: str
    sequence: str
    position: int
    frame: int
    split: str
    group: str
    offset: int  # neighbours at position -/+ offset (0: depth only)


@dataclass(frozen=True)
class ShardSpec:
    name: str
    split: str
    samples: tuple[SampleSpec, ...]


def encode_settings(dataset: str, params: Params) -> EncodeSettings:
    preprocess = params.preprocess
    if params.data.size < 1 or preprocess.neighbour_offset < 1:
        raise ValueError("data.size and preprocess.neighbour_offset must be positive")
    return EncodeSettings(
        dataset=dataset,
        size=params.data.size,
        neighbour_offset=preprocess.neighbour_offset,
        train_offsets=tuple(preprocess.train_offsets or [preprocess.neighbour_offset]),
        depth_unit=DEPTH_UNIT_CM.get(dataset, DEPTH_UNIT_CM["simcol"]),
        depth_only=dataset in DEPTH_ONLY_DATASETS,
        reader_params=json.dumps(params_to_dict(getattr(params.data, dataset)), sort_keys=True),
        withheld_fov_deg=params.data.assumed_fov_deg if preprocess.withhold_intrinsics else None,
    )


def plan_shards(
    sequences: list[Sequence], settings: EncodeSettings, samples_per_shard: int, shard_multiple: int
) -> list[ShardSpec]:
    """All shards of all splits, each with its samples, in a deterministic order."""
    if samples_per_shard < 1 or shard_multiple < 1:
        raise ValueError("preprocess.samples_per_shard and preprocess.shard_multiple must be positive")
    by_split: dict[str, list[SampleSpec]] = {split: [] for split in SPLITS}
    for sequence in sequences:
        if sequence.split not in by_split:
            raise DataFormatError(sequence.name, f"split must be one of {SPLITS}, found {sequence.split!r}")
        by_split[sequence.split].extend(sequence_samples(sequence, settings))
    check_unique_keys(s for samples in by_split.values() for s in samples)
    shards = []
    for split, samples in by_split.items():
        count = shard_count(len(samples), samples_per_shard, shard_multiple)
        for index in range(count):
            part = samples[len(samples) * index // count : len(samples) * (index + 1) // count]
            shards.append(ShardSpec(name=shard_name(split, index), split=split, samples=tuple(part)))
    return shards


def sequence_samples(sequence: Sequence, settings: EncodeSettings) -> list[SampleSpec]:
    """Target frames of a sequence: all of them when depth-only, else those with both neighbours.

    A neighbour is the frame exactly the target's offset in regular steps (:attr:`Sequence.frame_step`) before
    or after it, so no sample spans a gap in the frame numbers (the reader reports gaps). The offset is
    ``neighbour_offset``, or in the train split the entry of ``train_offsets`` at the target's position modulo
    their count.
    """
    if settings.depth_only:
        offsets = {i: 0 for i in range(len(sequence))}
    else:
        choices = settings.train_offsets if sequence.split == "train" else (settings.neighbour_offset,)
        valid = {offset: set(targets_with_neighbours(sequence.frame_ids, offset, sequence.frame_step))
                 for offset in set(choices)}
        offsets = {i: choices[i % len(choices)] for i in range(len(sequence))
                   if i in valid[choices[i % len(choices)]]}
    return [
        SampleSpec(
            key=sample_key(settings.dataset, sequence.name, sequence.frame_ids[i]),
            sequence=sequence.name,
            position=i,
            frame=int(sequence.frame_ids[i]),
            split=sequence.split,
            group=sequence.group,
            offset=offset,
        )
        for i, offset in offsets.items()
    ]


def targets_with_neighbours(frame_ids: list[int], offset: int, step: int) -> list[int]:
    """Positions ``i`` whose frames at positions ``i -/+ offset`` are numbered ``frame -/+ offset * step``."""
    span = offset * step
    return [
        i
        for i in range(offset, len(frame_ids) - offset)
        if frame_ids[i - offset] == frame_ids[i] - span and frame_ids[i + offset] == frame_ids[i] + span
    ]


def sample_key(dataset: str, sequence: str, frame: int) -> str:
    """``<dataset>-<sequence>-<frame:06d>`` with anything but letters, digits, ``_``, ``-`` made ``_``.

    WebDataset splits a member name at its first dot (and treats ``/`` as a folder), so neither may appear.
    """
    return f"{dataset}-{slug(sequence)}-{frame:06d}"


def check_unique_keys(samples: Iterable[SampleSpec]) -> None:
    seen: dict[str, str] = {}
    for sample in samples:
        if sample.key in seen:
            raise DataFormatError(
                sample.sequence, f"sample key {sample.key} also produced by sequence {seen[sample.key]!r}"
            )
        seen[sample.key] = sample.sequence


def shard_count(samples: int, samples_per_shard: int, multiple: int) -> int:
    """Fewest shards holding at most ``samples_per_shard`` each, rounded up to a multiple of ``multiple``."""
    if samples == 0:
        return 0
    return math.ceil(math.ceil(samples / samples_per_shard) / multiple) * multiple


def sample_positions(spec: SampleSpec, settings: EncodeSettings) -> list[int]:
    """Positions of the frames a sample is built from: ``cur``, and ``prev`` / ``next`` unless depth-only."""
    i, offset = spec.position, spec.offset
    return [i] if settings.depth_only else [i - offset, i, i + offset]


def samples_without_pose(shards: list[ShardSpec], sequences: list[Sequence], settings: EncodeSettings) -> int:
    """Samples of sequences that have poses where a frame read (prev, cur or next) has none.

    They are written with that pose null in ``meta.json`` (the reader reported why: no pose row, or NaN /
    inf in the pose file); the preprocess summary counts them so that none passes unnoticed.
    """
    by_name = {sequence.name: sequence for sequence in sequences}
    return sum(
        by_name[spec.sequence].poses is not None
        and any(by_name[spec.sequence].pose(p) is None for p in sample_positions(spec, settings))
        for shard in shards
        for spec in shard.samples
    )


def shard_keys(shards: list[ShardSpec], settings: EncodeSettings, sequences: list[Sequence]) -> dict[str, str]:
    """Per shard name, a hash of everything the shard is built from.

    That is the format version and encode settings, the shard's samples, and for every frame a sample
    reads: its number and pose, the sequence's K and image size, and the path, size and ``mtime_ns`` of
    each file it is decoded from (:meth:`Sequence.frame_files`). A shard left by an interrupted run is
    reused only while its key is unchanged, so an input changed in between (new pixels, a corrected pose)
    rebuilds exactly the shards built from it. Sizes and times, not content hashes: hashing every image
    would cost a read of the whole dataset on each run.
    """
    by_name = {sequence.name: sequence for sequence in sequences}
    records = FrameRecords()
    common = json.dumps({"version": FORMAT_VERSION, "settings": asdict(settings)}, sort_keys=True)
    keys = {}
    for shard in shards:
        digest = hashlib.sha256(common.encode())
        digest.update(shard.name.encode())
        for spec in shard.samples:
            sequence = by_name[spec.sequence]
            frames = [records.frame(sequence, position) for position in sample_positions(spec, settings)]
            digest.update(json.dumps([asdict(spec), records.camera(sequence), frames]).encode())
        keys[shard.name] = digest.hexdigest()
    return keys


class FrameRecords:
    """JSON-ready descriptions of frames and cameras for :func:`shard_keys`, each made once.

    A frame is read by up to three samples and a camera by every sample of its sequence.
    """

    def __init__(self) -> None:
        self.frames: dict[tuple[str, int], list] = {}
        self.cameras: dict[str, list] = {}

    def frame(self, sequence: Sequence, position: int) -> list:
        key = (sequence.name, position)
        if key not in self.frames:
            pose = sequence.pose(position)
            self.frames[key] = [
                int(sequence.frame_ids[position]),
                None if pose is None else np.asarray(pose, dtype=np.float64).tolist(),
                [file_state(path) for path in sequence.frame_files(position)],
            ]
        return self.frames[key]

    def camera(self, sequence: Sequence) -> list:
        if sequence.name not in self.cameras:
            K = np.asarray(sequence.K, dtype=np.float64).tolist()
            self.cameras[sequence.name] = [sequence.name, list(sequence.image_size), K]
        return self.cameras[sequence.name]


def file_state(path: Path) -> list:
    """``[path, size, mtime_ns]`` of a source file: what tells a changed file from the one a shard read."""
    try:
        status = Path(path).stat()
    except OSError as exc:
        raise DataFormatError(path, f"source file listed by the reader cannot be read ({exc.strerror})") from None
    return [str(path), status.st_size, status.st_mtime_ns]

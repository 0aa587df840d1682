"""Preprocessing: dataset sequences -> WebDataset shards of target frames with their neighbours.

Output of :func:`preprocess_dataset` (schema in ``docs/design.md``)::

    <out_dir>/train-000000.tar ... val-000000.tar ... test-000000.tar     manifest.parquet

Each sample (tar members ``<key>.<ext>``, WebDataset's naming) is one target frame ``cur`` with its
neighbours ``prev`` / ``next`` at ``-/+ preprocess.neighbour_offset``:

- ``prev.png``, ``cur.png``, ``next.png``: RGB ``uint8``, centre-cropped to a square and resized to
  ``data.size`` with ``cv2.INTER_AREA``.
- ``depth.png``: ``uint16`` z-depth of ``cur`` with ``depth_cm = value * meta.depth_unit``; 0 = unknown
  (also where the dataset has no depth, or the depth exceeds the encodable range ``65535 * depth_unit``).
  Resized by nearest neighbour with pixel centres aligned (``cv2.INTER_NEAREST_EXACT``), so no depth value
  is invented across an edge.
- ``meta.json``: ``dataset``, ``sequence``, ``group``, ``split``, ``frame`` (the dataset's frame number of
  ``cur``), ``frame_ids`` (``prev``/``cur``/``next``), ``K`` (3x3 at the stored size, pixel centres at
  integers), ``T_world_cam`` (``prev``/``cur``/``next``: 4x4 camera-to-world, cm, or null), ``depth_unit``
  (cm per count), ``native_size`` ``[H, W]``.

Depth-only datasets (SceneNet, for the latent bank) store every frame as a sample with only ``depth.png``
and ``meta.json`` (``prev``/``next`` poses and frame ids null).

Shards: each split's samples, in sequence order, are spread evenly (sizes differ by at most one) over a
shard count that is a multiple of ``preprocess.shard_multiple``, so whole shards divide evenly over that
many training workers. Keys (``<dataset>-<sequence>-<frame>``) depend only on the data, never on the run.

Runs are atomic and resumable: everything is written into ``.<out_dir name>.partial/`` beside ``out_dir``
together with a plan fingerprint; each shard is written under a temporary name and renamed when complete.
A rerun with the same plan keeps the finished shards and writes the rest; only a complete result replaces
``out_dir``, so an interrupted run never leaves half shards there. Shards are written by a pool of
``preprocess.workers`` processes; each decodes and resizes a frame once even though three samples use it.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import multiprocessing
import os
import re
import shutil
import sys
import tarfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Optional

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from endoflow.config import Params
from endoflow.data.base import DataFormatError, Sequence
from endoflow.data.registry import open_reader
from endoflow.geometry.camera import scale_intrinsics

SPLITS = ("train", "val", "test")
DATASETS = ("simcol", "endoslam", "scenenet")
DEPTH_ONLY_DATASETS = frozenset({"scenenet"})
# cm per stored depth count: colon data up to 65.535 cm at 10 um steps (finer than SimCol3D's own 0.078 cm);
# indoor scenes up to 65.5 m at 1 mm.
DEPTH_UNIT_CM = {"simcol": 0.001, "endoslam": 0.001, "scenenet": 0.1}
MANIFEST = "manifest.parquet"
# Parquet schema metadata key holding {shard name: sample count}, empty shards included.
SHARD_COUNTS_KEY = b"endoflow.shard_samples"
PLAN_FILE = "plan.json"
# Bumped whenever the bytes written for the same input change, so stale partial runs are not reused.
FORMAT_VERSION = 1
_TMP_MARK = ".tmp-"


@dataclass(frozen=True)
class EncodeSettings:
    """How samples of one dataset are written (identical in every worker)."""

    dataset: str
    size: int
    neighbour_offset: int
    depth_unit: float
    depth_only: bool


@dataclass(frozen=True)
class SampleSpec:
    """One planned sample: target frame ``position`` (index into the sequence) and its key."""

    key: str
    sequence: str
    position: int
    frame: int
    split: str
    group: str


@dataclass(frozen=True)
class ShardSpec:
    name: str
    split: str
    samples: tuple[SampleSpec, ...]


@dataclass(frozen=True)
class ShardResult:
    name: str
    samples: int
    frames_decoded: int
    depth_out_of_range: int


@dataclass(frozen=True)
class ReaderSequences:
    """Picklable ``() -> list[Sequence]`` opening a dataset through the registry (run in each worker)."""

    root: str
    dataset: str
    params: Params

    def __call__(self) -> list[Sequence]:
        return open_reader(self.root, self.dataset, self.params).sequences()


# ------------------------------------------------------------------------------------------ entry points
def preprocess_dataset(dataset: str, params: Params, out_dir: Path) -> dict:
    """Write the shards and manifest of ``dataset`` (``simcol``, ``endoslam``, ``scenenet``) into ``out_dir``.

    Reads ``params.data.<dataset>.root`` through :func:`endoflow.data.registry.open_reader`.

    Returns:
        Summary: samples and shards per split, shards reused from an interrupted run, frames decoded,
        depth pixels beyond the encodable range, seconds and frames per second.
    """
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {dataset!r}; expected one of {', '.join(DATASETS)}")
    root = getattr(params.data, dataset).root
    return write_dataset_shards(ReaderSequences(root, dataset, params), dataset, params, out_dir)


def write_dataset_shards(
    load_sequences: Callable[[], list[Sequence]], dataset: str, params: Params, out_dir: Path
) -> dict:
    """:func:`preprocess_dataset` for any source of sequences.

    ``load_sequences`` is called once here and once in every worker process, so with
    ``preprocess.workers > 1`` it must be picklable (a module-level function or a dataclass instance) and
    return the same sequences each time.
    """
    started = time.perf_counter()
    settings = encode_settings(dataset, params)
    sequences = load_sequences()
    shards = plan_shards(sequences, settings, params.preprocess.samples_per_shard, params.preprocess.shard_multiple)
    out_dir = Path(out_dir)
    staging = out_dir.parent / f".{out_dir.name}.partial"
    reused = prepare_staging(staging, plan_fingerprint(shards, settings, sequences), shards)
    todo = [shard for shard in shards if shard.name not in reused]
    results = run_shard_writers(todo, staging, settings, sequences, load_sequences, params.preprocess.workers)
    write_manifest(staging / MANIFEST, shards, dataset)
    (staging / PLAN_FILE).unlink()
    replace_directory(staging, out_dir)
    seconds = time.perf_counter() - started
    frames = sum(r.frames_decoded for r in results)
    return {
        "dataset": dataset,
        "out_dir": str(out_dir),
        "samples": {split: sum(len(s.samples) for s in shards if s.split == split) for split in SPLITS},
        "shards": {split: sum(1 for s in shards if s.split == split) for split in SPLITS},
        "shards_reused": len(reused),
        "frames_decoded": frames,
        "depth_out_of_range_pixels": sum(r.depth_out_of_range for r in results),
        "seconds": round(seconds, 3),
        "frames_per_second": round(frames / seconds, 1) if seconds > 0 else 0.0,
    }


def encode_settings(dataset: str, params: Params) -> EncodeSettings:
    if params.data.size < 1 or params.preprocess.neighbour_offset < 1:
        raise ValueError("data.size and preprocess.neighbour_offset must be positive")
    return EncodeSettings(
        dataset=dataset,
        size=params.data.size,
        neighbour_offset=params.preprocess.neighbour_offset,
        depth_unit=DEPTH_UNIT_CM.get(dataset, DEPTH_UNIT_CM["simcol"]),
        depth_only=dataset in DEPTH_ONLY_DATASETS,
    )


# ----------------------------------------------------------------------------------------------- planning
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
            shards.append(ShardSpec(name=f"{split}-{index:06d}.tar", split=split, samples=tuple(part)))
    return shards


def sequence_samples(sequence: Sequence, settings: EncodeSettings) -> list[SampleSpec]:
    """Target frames of a sequence: all of them when depth-only, else those with both neighbours."""
    margin = 0 if settings.depth_only else settings.neighbour_offset
    return [
        SampleSpec(
            key=sample_key(settings.dataset, sequence.name, sequence.frame_ids[i]),
            sequence=sequence.name,
            position=i,
            frame=int(sequence.frame_ids[i]),
            split=sequence.split,
            group=sequence.group,
        )
        for i in range(margin, len(sequence) - margin)
    ]


def sample_key(dataset: str, sequence: str, frame: int) -> str:
    """``<dataset>-<sequence>-<frame:06d>`` with anything but letters, digits, ``_``, ``-`` made ``_``.

    WebDataset splits a member name at its first dot (and treats ``/`` as a folder), so neither may appear.
    """
    slug = re.sub(r"[^A-Za-z0-9_-]", "_", sequence)
    return f"{dataset}-{slug}-{frame:06d}"


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


def plan_fingerprint(shards: list[ShardSpec], settings: EncodeSettings, sequences: list[Sequence]) -> str:
    """Hash of everything that determines the shards' bytes except the image files' contents."""
    digest = hashlib.sha256()
    digest.update(json.dumps({"version": FORMAT_VERSION, "settings": asdict(settings)}, sort_keys=True).encode())
    for sequence in sequences:
        digest.update(json.dumps([sequence.name, list(sequence.image_size)]).encode())
        digest.update(np.ascontiguousarray(sequence.K, dtype=np.float64).tobytes())
        if sequence.poses is not None:
            digest.update(np.ascontiguousarray(sequence.poses, dtype=np.float64).tobytes())
    for shard in shards:
        digest.update(json.dumps([shard.name, [asdict(s) for s in shard.samples]]).encode())
    return digest.hexdigest()


# ------------------------------------------------------------------------------------ staging and output
def prepare_staging(staging: Path, fingerprint: str, shards: list[ShardSpec]) -> set[str]:
    """Make ``staging`` ready for this plan; returns the names of shards already complete there.

    A staging folder from the same plan keeps its finished shards (temporary files are dropped); any other
    content is discarded.
    """
    plan_path = staging / PLAN_FILE
    if plan_path.is_file() and json.loads(plan_path.read_text()).get("fingerprint") == fingerprint:
        for leftover in staging.glob(f"*{_TMP_MARK}*"):
            leftover.unlink()
        return {shard.name for shard in shards if (staging / shard.name).is_file()}
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    write_bytes_atomic(plan_path, json.dumps({"fingerprint": fingerprint}).encode())
    return set()


def replace_directory(staging: Path, out_dir: Path) -> None:
    """Put the complete ``staging`` folder in place of ``out_dir``.

    The old output is moved aside (not deleted) until the new one is in place.
    """
    old = out_dir.parent / f".{out_dir.name}.old"
    if old.exists():
        shutil.rmtree(old)
    if out_dir.exists():
        os.replace(out_dir, old)
    os.replace(staging, out_dir)
    if old.exists():
        shutil.rmtree(old)


def write_manifest(path: Path, shards: list[ShardSpec], dataset: str) -> None:
    """``manifest.parquet``: one row per sample; per-shard counts (empty shards too) in the schema metadata."""
    rows = [(shard.name, sample) for shard in shards for sample in shard.samples]
    table = pa.table(
        {
            "shard": pa.array([name for name, _ in rows], pa.string()),
            "key": pa.array([s.key for _, s in rows], pa.string()),
            "dataset": pa.array([dataset] * len(rows), pa.string()),
            "sequence": pa.array([s.sequence for _, s in rows], pa.string()),
            "group": pa.array([s.group for _, s in rows], pa.string()),
            "frame": pa.array([s.frame for _, s in rows], pa.int64()),
            "split": pa.array([s.split for _, s in rows], pa.string()),
        }
    )
    counts = json.dumps({shard.name: len(shard.samples) for shard in shards})
    table = table.replace_schema_metadata({SHARD_COUNTS_KEY: counts.encode()})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    write_bytes_atomic(path, sink.getvalue().to_pybytes())


def write_bytes_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f"{path.name}{_TMP_MARK}{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------------- shard writing
_WORKER_SEQUENCES: dict[str, Sequence] = {}


def run_shard_writers(
    shards: list[ShardSpec],
    staging: Path,
    settings: EncodeSettings,
    sequences: list[Sequence],
    load_sequences: Callable[[], list[Sequence]],
    workers: int,
) -> list[ShardResult]:
    """Write ``shards`` into ``staging``, in this process (``workers <= 1``) or a process pool."""
    if workers <= 1 or len(shards) <= 1:
        by_name = {s.name: s for s in sequences}
        with single_threaded_opencv():
            return [write_shard(shard, staging, settings, by_name) for shard in shards]
    with ProcessPoolExecutor(
        max_workers=min(workers, len(shards)),
        mp_context=pool_context(),
        initializer=_init_worker,
        initargs=(load_sequences,),
    ) as pool:
        futures = [pool.submit(_write_shard_in_worker, shard, staging, settings) for shard in shards]
        try:
            return [future.result() for future in futures]
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def pool_context() -> multiprocessing.context.BaseContext:
    """How worker processes start.

    ``fork`` where it is safe (Linux, no other thread in this process): workers start at once with
    everything already imported, which matters when the work takes seconds. Otherwise a fork server (a clean
    single-threaded process, so threads of Ray or torch are never inherited in an undefined state) with
    this module preloaded, or ``spawn`` where there is no fork server.
    """
    methods = multiprocessing.get_all_start_methods()
    if sys.platform.startswith("linux") and threading.active_count() == 1:
        return multiprocessing.get_context("fork")
    if "forkserver" in methods:
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload([__name__])
        return context
    return multiprocessing.get_context("spawn")


def _init_worker(load_sequences: Callable[[], list[Sequence]]) -> None:
    # Parallelism comes from the processes; OpenCV's own threads would only compete with them.
    cv2.setNumThreads(1)
    _WORKER_SEQUENCES.clear()
    _WORKER_SEQUENCES.update({s.name: s for s in load_sequences()})


def _write_shard_in_worker(shard: ShardSpec, staging: Path, settings: EncodeSettings) -> ShardResult:
    return write_shard(shard, staging, settings, _WORKER_SEQUENCES)


@contextmanager
def single_threaded_opencv() -> Iterator[None]:
    """OpenCV single-threaded inside, as in the pool's workers (a fair one-process figure); restored after."""
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(previous)


def write_shard(
    shard: ShardSpec, staging: Path, settings: EncodeSettings, sequences: dict[str, Sequence]
) -> ShardResult:
    """Encode the samples of ``shard`` and write them as one tar, renamed into place when complete."""
    final = staging / shard.name
    tmp = staging / f"{shard.name}{_TMP_MARK}{os.getpid()}"
    cache = FrameCache(settings)
    out_of_range = 0
    with tarfile.open(tmp, "w", format=tarfile.PAX_FORMAT) as tar:
        for spec in shard.samples:
            files, bad_depth = encode_sample(spec, sequences[spec.sequence], settings, cache)
            out_of_range += bad_depth
            for extension in sorted(files):
                add_member(tar, f"{spec.key}.{extension}", files[extension])
    os.replace(tmp, final)
    frames = len(shard.samples) if settings.depth_only else cache.decoded
    return ShardResult(shard.name, len(shard.samples), frames, out_of_range)


def add_member(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    """Add a file with fixed metadata, so the same samples give byte-identical tars."""
    info = tarfile.TarInfo(name)
    info.size = len(data)
    info.mode = 0o444
    info.mtime = 0
    tar.addfile(info, io.BytesIO(data))


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

    def evict_before(self, position: int) -> None:
        for old in [p for p in self.frames if p < position]:
            del self.frames[old]


def encode_sample(
    spec: SampleSpec, sequence: Sequence, settings: EncodeSettings, cache: FrameCache
) -> tuple[dict[str, bytes], int]:
    """The files of one sample (extension -> bytes) and its count of depth pixels beyond range."""
    i, offset = spec.position, settings.neighbour_offset
    positions = {"cur": i} if settings.depth_only else {"prev": i - offset, "cur": i, "next": i + offset}
    files: dict[str, bytes] = {}
    if not settings.depth_only:
        cache.evict_before(i - offset)
        for name, position in positions.items():
            files[f"{name}.png"] = cache.rgb_png(sequence, position)
    depth_counts, out_of_range = depth_to_counts(stored_depth(sequence, i, settings.size), settings.depth_unit)
    files["depth.png"] = encode_png(depth_counts)
    files["meta.json"] = json.dumps(sample_meta(spec, sequence, positions, settings), sort_keys=True).encode()
    return files, out_of_range


def sample_meta(
    spec: SampleSpec, sequence: Sequence, positions: dict[str, int], settings: EncodeSettings
) -> dict:
    names = ("prev", "cur", "next")
    poses = {name: _pose_list(sequence, positions[name]) if name in positions else None for name in names}
    frame_ids = {name: int(sequence.frame_ids[positions[name]]) if name in positions else None for name in names}
    return {
        "dataset": settings.dataset,
        "sequence": spec.sequence,
        "group": spec.group,
        "split": spec.split,
        "frame": spec.frame,
        "frame_ids": frame_ids,
        "K": stored_intrinsics(sequence.K, sequence.image_size, settings.size).tolist(),
        "T_world_cam": poses,
        "depth_unit": settings.depth_unit,
        "native_size": [int(sequence.image_size[0]), int(sequence.image_size[1])],
    }


def _pose_list(sequence: Sequence, position: int) -> Optional[list[list[float]]]:
    pose = sequence.pose(position)
    return None if pose is None else np.asarray(pose, dtype=np.float64).tolist()


# -------------------------------------------------------------------------------------- image operations
def centre_square(height: int, width: int) -> tuple[int, int, int]:
    """``(top, left, side)`` of the largest centred square."""
    side = min(height, width)
    return (height - side) // 2, (width - side) // 2, side


def stored_intrinsics(K: np.ndarray, native_size: tuple[int, int], size: int) -> np.ndarray:
    """K of the native image after the centre crop to a square and the resize to ``size x size``."""
    top, left, side = centre_square(*native_size)
    cropped = np.array(K, dtype=np.float64)
    cropped[0, 2] -= left
    cropped[1, 2] -= top
    scale = size / side
    return scale_intrinsics(cropped, scale, scale)


def resize_rgb(rgb: np.ndarray, size: int) -> np.ndarray:
    top, left, side = centre_square(*rgb.shape[:2])
    square = rgb[top : top + side, left : left + side]
    return cv2.resize(square, (size, size), interpolation=cv2.INTER_AREA)


def resize_depth(depth: np.ndarray, size: int) -> np.ndarray:
    top, left, side = centre_square(*depth.shape[:2])
    square = np.ascontiguousarray(depth[top : top + side, left : left + side])
    # NEAREST_EXACT samples the source pixel under each target pixel's centre (plain NEAREST is off by
    # half a pixel), keeping depth registered with the INTER_AREA colour image and K.
    return cv2.resize(square, (size, size), interpolation=cv2.INTER_NEAREST_EXACT)


def stored_depth(sequence: Sequence, position: int, size: int) -> np.ndarray:
    """``size x size`` float32 z-depth in cm of a frame; zeros (unknown) when the dataset has none."""
    if sequence.load_depth is None:
        return np.zeros((size, size), np.float32)
    depth = sequence.load_depth(position)
    check_frame(depth, sequence, position, channels=None)
    return resize_depth(np.asarray(depth, dtype=np.float32), size)


def depth_to_counts(depth_cm: np.ndarray, unit: float) -> tuple[np.ndarray, int]:
    """``uint16`` counts of ``unit`` cm; non-finite, non-positive and out-of-range depths become 0."""
    counts = np.round(np.nan_to_num(depth_cm, nan=0.0, posinf=0.0, neginf=0.0) / unit)
    too_far = counts > np.iinfo(np.uint16).max
    counts[too_far | (counts < 0)] = 0
    return counts.astype(np.uint16), int(too_far.sum())


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an RGB ``uint8`` or single-channel ``uint16`` image."""
    pixels = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    ok, data = cv2.imencode(".png", pixels)
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {image.shape}, {image.dtype}")
    return data.tobytes()


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

"""Preprocessing: dataset sequences -> WebDataset shards of target frames with their neighbours.

Output of :func:`preprocess_dataset`: a shard folder in the format that :mod:`endoflow.data.shard_format`
defines (member names, depth encoding, the manifest with every shard's sample count and SHA-256). Each sample
is one target frame ``cur`` with its neighbours ``prev`` / ``next`` at ``-/+ preprocess.neighbour_offset``:
RGB centre-cropped to a square and resized to ``data.size`` with ``cv2.INTER_AREA``; depth resized by nearest
neighbour with pixel centres aligned (``cv2.INTER_NEAREST_EXACT``), so no depth value is invented across an
edge, in counts of ``DEPTH_UNIT_CM[dataset]`` (0 where unknown, where the dataset has no depth, or beyond the
encodable range ``65535 * depth_unit``). Depth-only datasets (SceneNet, for the latent bank) store every frame
as a sample with only ``depth.png`` and ``meta.json`` (``prev``/``next`` poses and frame ids null).

Wrong but decodable input: a target is taken only when its neighbours are the frames exactly
``neighbour_offset`` regular frame steps away, so no sample spans a missing frame (the reader warns about
gaps). A frame without a pose (none in the data, or NaN / inf in the pose file: the reader warns, naming the
file and frames) keeps its sample, whose images are sound, with that pose null in ``meta.json``; the summary
counts such samples (``samples_without_pose``). A non-finite value is never written as a pose.

Shards: each split's samples, in sequence order, are spread evenly (sizes differ by at most one) over a
shard count that is a multiple of ``preprocess.shard_multiple``, so whole shards divide evenly over that
many training workers. Keys (``<dataset>-<sequence>-<frame>``) depend only on the data, never on the run.

Runs are atomic and resumable: everything is written into a staging folder (:class:`OutputFolder`)
together with a plan file holding each shard's key (:func:`shard_keys`: its samples, settings, poses, K and
the size and mtime of every source file it reads); each shard appears whole under its name or not at all
(:func:`endoflow.io.atomic_location`). A rerun keeps a finished shard only if its key is unchanged
(``shards_reused`` in the summary) and writes the rest, so a shard is never reused after an input it was
built from changed. The output is a local path or an fsspec URL. On a filesystem (a path, ``file://``, a
shared mount) the staging folder is ``.<out name>.partial/`` beside the output and only a complete result
replaces the output, so an interrupted run never leaves half shards there. An object store (``s3://``) has no
rename: the shards are written in place, the old manifest removed first and the new one written last, so a
reader finds either no manifest (and says to run the preprocess stage) or the complete new output.

Engines (``preprocess.engine``): ``local`` writes shards in this process or a pool of ``preprocess.workers``
processes; ``ray`` runs one Ray task per shard on the cluster at ``ray.address`` (a local Ray when it is null,
:func:`endoflow.ray_runtime.connect_ray`), each task writing its shard to the output location and returning
its typed :class:`ShardResult`. Shards of equal size make equal tasks, however long a sequence is. Either
way this process plans the shards, keeps the resume keys, reports progress with the time left as shards
complete, and writes the manifest, so both engines write the same bytes. Each shard decodes and resizes a
frame once even though three samples use it.
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import posixpath
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Optional

import cv2
import fsspec
import numpy as np
import webdataset as wds
from fsspec.implementations.local import LocalFileSystem

from endoflow.config import Params, RayConfig, params_to_dict
from endoflow.data.base import DATASETS, DEPTH_ONLY_DATASETS, DataFormatError, Sequence, slug
from endoflow.data.registry import open_reader
from endoflow.data.shard_format import (
    DEPTH_MEMBER,
    FORMAT_VERSION,
    IMAGE_NAMES,
    MANIFEST,
    META_MEMBER,
    SPLITS,
    HashingWriter,
    ShardEntry,
    manifest_bytes,
    sample_sha256,
    shard_digests,
    shard_name,
)
from endoflow.geometry.camera import scale_intrinsics
from endoflow.io import atomic_location, replace_directory, write_bytes
from endoflow.locations import absolute_location
from endoflow.progress import format_duration
from endoflow.ray_runtime import connect_ray

# cm per stored depth count: colon data up to 65.535 cm at 10 um steps (finer than SimCol3D's own 0.078 cm);
# indoor scenes up to 65.5 m at 1 mm.
DEPTH_UNIT_CM = {"simcol": 0.001, "endoslam": 0.001, "scenenet": 0.1}
PLAN_FILE = "plan.json"
# TarWriter streams 10 KiB tar records; a large file buffer makes them few large writes (bench_tar_writer.py).
WRITE_BUFFER = 8 << 20
# Seconds between progress lines while shards are written (the last shard always gets one).
PROGRESS_INTERVAL_S = 10.0
# Ray tasks queued per cluster CPU: enough that no CPU waits for the driver, few enough that the object
# store holds only the sequences of shards in flight (SceneNet has millions of frames).
RAY_TASKS_PER_CPU = 2


@dataclass(frozen=True)
class EncodeSettings:
    """How samples of one dataset are written (identical in every worker)."""

    dataset: str
    size: int
    neighbour_offset: int
    depth_unit: float
    depth_only: bool
    # data.<dataset> as JSON: reader settings (depth scale, units, intrinsics...) change the decoded frames
    # without changing any file, so they are part of every shard's resume key
    reader_params: str


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
    entry: ShardEntry  # what the manifest records of the shard, hashed as it was written
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
def preprocess_dataset(dataset: str, params: Params, out_dir: str | Path) -> dict:
    """Write the shards and manifest of ``dataset`` (``simcol``, ``endoslam``, ``scenenet``) into ``out_dir``.

    Reads ``params.data.<dataset>.root`` (made absolute against the working folder: Ray tasks run in their
    own folders) through :func:`endoflow.data.registry.open_reader`. ``out_dir`` is a path or an fsspec URL.

    Returns:
        Summary: samples and shards per split, shards reused from an interrupted run, samples written with
        a null pose because a frame they read has none (``samples_without_pose``), frames decoded, depth
        pixels beyond the encodable range, seconds and frames per second.
    """
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {dataset!r}; expected one of {', '.join(DATASETS)}")
    root = absolute_location(getattr(params.data, dataset).root, Path.cwd())
    return write_dataset_shards(ReaderSequences(root, dataset, params), dataset, params, out_dir)


def write_dataset_shards(
    load_sequences: Callable[[], list[Sequence]], dataset: str, params: Params, out_dir: str | Path
) -> dict:
    """:func:`preprocess_dataset` for any source of sequences.

    ``load_sequences`` is called once here and, with the local engine and ``preprocess.workers > 1``, once in
    every worker process, so it must then be picklable (a module-level function or a dataclass instance) and
    return the same sequences each time. The Ray engine sends each task the sequences its shard reads.
    """
    started = time.perf_counter()
    settings = encode_settings(dataset, params)
    sequences = load_sequences()
    shards = plan_shards(sequences, settings, params.preprocess.samples_per_shard, params.preprocess.shard_multiple)
    output = OutputFolder.of(str(out_dir))
    reused = prepare_staging(output.staging, shard_keys(shards, settings, sequences))
    todo = [shard for shard in shards if shard.name not in reused]
    progress = ShardProgress(dataset, total=len(todo), kept=len(reused))
    if params.preprocess.engine == "ray":
        results = run_shard_tasks_on_ray(todo, output.staging, settings, sequences, params.ray, progress)
    else:
        results = run_shard_writers(todo, output.staging, settings, sequences, load_sequences,
                                    params.preprocess.workers, progress)
    entries = {r.entry.name: r.entry for r in results}
    entries.update({s.name: kept_shard_entry(output.staging, s) for s in shards if s.name in reused})
    write_manifest(output.staging, shards, dataset, entries)
    output.publish()
    seconds = time.perf_counter() - started
    frames = sum(r.frames_decoded for r in results)
    return {
        "dataset": dataset,
        "out_dir": str(out_dir),
        "samples": {split: sum(len(s.samples) for s in shards if s.split == split) for split in SPLITS},
        "shards": {split: sum(1 for s in shards if s.split == split) for split in SPLITS},
        "shards_reused": len(reused),
        "samples_without_pose": samples_without_pose(shards, sequences, settings),
        "frames_decoded": frames,
        "depth_out_of_range_pixels": sum(r.depth_out_of_range for r in results),
        "seconds": round(seconds, 3),
        "frames_per_second": round(frames / seconds, 1) if seconds > 0 else 0.0,
    }


def format_preprocess_summary(summary: dict) -> str:
    """The closing lines of the ``preprocess`` stage, from :func:`write_dataset_shards`' summary."""
    samples, shards = summary["samples"], summary["shards"]
    splits = ", ".join(f"{split} {samples[split]} samples in {shards[split]} shards" for split in SPLITS)
    lines = [f"[preprocess] {summary['dataset']} done: {splits}; {summary['shards_reused']} shards kept from an "
             f"interrupted run; {summary['frames_decoded']} frames decoded in {summary['seconds']:.1f} s "
             f"({summary['frames_per_second']:.1f} frames/s)",
             f"[preprocess] written to {summary['out_dir']}"]
    if summary["samples_without_pose"]:
        lines.append(f"[preprocess] warning: {summary['samples_without_pose']} samples have no pose (depth only)")
    if summary["depth_out_of_range_pixels"]:
        lines.append(f"[preprocess] warning: {summary['depth_out_of_range_pixels']} depth pixels beyond the "
                     "16-bit range were stored as invalid (0)")
    return "\n".join(lines) + "\n"


def encode_settings(dataset: str, params: Params) -> EncodeSettings:
    if params.data.size < 1 or params.preprocess.neighbour_offset < 1:
        raise ValueError("data.size and preprocess.neighbour_offset must be positive")
    return EncodeSettings(
        dataset=dataset,
        size=params.data.size,
        neighbour_offset=params.preprocess.neighbour_offset,
        depth_unit=DEPTH_UNIT_CM.get(dataset, DEPTH_UNIT_CM["simcol"]),
        depth_only=dataset in DEPTH_ONLY_DATASETS,
        reader_params=json.dumps(params_to_dict(getattr(params.data, dataset)), sort_keys=True),
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
            shards.append(ShardSpec(name=shard_name(split, index), split=split, samples=tuple(part)))
    return shards


def sequence_samples(sequence: Sequence, settings: EncodeSettings) -> list[SampleSpec]:
    """Target frames of a sequence: all of them when depth-only, else those with both neighbours.

    A neighbour is the frame exactly ``neighbour_offset`` regular steps (:attr:`Sequence.frame_step`)
    before or after the target, so no sample spans a gap in the frame numbers (the reader reports gaps).
    """
    if settings.depth_only:
        targets = range(len(sequence))
    else:
        targets = targets_with_neighbours(sequence.frame_ids, settings.neighbour_offset, sequence.frame_step)
    return [
        SampleSpec(
            key=sample_key(settings.dataset, sequence.name, sequence.frame_ids[i]),
            sequence=sequence.name,
            position=i,
            frame=int(sequence.frame_ids[i]),
            split=sequence.split,
            group=sequence.group,
        )
        for i in targets
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
    i, offset = spec.position, settings.neighbour_offset
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


# ------------------------------------------------------------------------------------ staging and output
@dataclass(frozen=True)
class OutputFolder:
    """Where a run writes (``staging``, a path or an fsspec URL) and where its complete result goes (``final``).

    On a filesystem (a path or ``file://``, local or a shared mount) staging is ``.<name>.partial/`` beside
    the output, swapped in whole by :func:`endoflow.io.replace_directory`. An object store has no rename, so
    staging is the output itself: :func:`prepare_staging` removes the old manifest first, and
    :meth:`publish` leaves the manifest, written last, as the point where the new output is complete.
    """

    final: str
    staging: str

    @classmethod
    def of(cls, out: str) -> "OutputFolder":
        fs, path = fsspec.core.url_to_fs(out)
        if isinstance(fs, LocalFileSystem):
            final = Path(path)
            return cls(str(final), str(final.parent / f".{final.name}.partial"))
        url = out.rstrip("/")
        return cls(url, url)

    def publish(self) -> None:
        """The plan file removed; the staging folder put in place of the output unless it is the output."""
        fs, path = fsspec.core.url_to_fs(posixpath.join(self.staging, PLAN_FILE))
        fs.rm(path)
        if self.staging != self.final:
            replace_directory(self.staging, self.final)


def prepare_staging(staging: str, keys: dict[str, str]) -> set[str]:
    """Make ``staging`` ready for a plan whose shards have ``keys``; returns the names of shards kept.

    A finished shard is kept only when the key recorded for it in the staging folder's plan file equals
    its key now. Everything else (stale shards, temporaries, leftovers of another plan) is removed before
    the new keys are recorded, so a recorded key always describes the shard file of that name, or one not
    written yet. A manifest goes first: where staging is the output itself (an object store), readers then
    never pair it with shards that are going away.
    """
    fs, folder = fsspec.core.url_to_fs(staging)
    fs.makedirs(folder, exist_ok=True)
    recorded = recorded_keys(posixpath.join(staging, PLAN_FILE))
    present = folder_entries(fs, folder)
    kept = {name for name, key in keys.items() if recorded.get(name) == key and name in present
            and fs.isfile(present[name])}
    for name in sorted(present, key=lambda name: name != MANIFEST):
        if name not in kept and name != PLAN_FILE:
            fs.rm(present[name], recursive=True)
    plan = json.dumps({"shard_keys": keys}, indent=1, sort_keys=True).encode()
    write_bytes(posixpath.join(staging, PLAN_FILE), plan)
    return kept


def folder_entries(fs: fsspec.AbstractFileSystem, folder: str) -> dict[str, str]:
    """Name -> path of what ``folder`` holds; nothing when it does not exist (an object store's empty prefix)."""
    try:
        paths = fs.ls(folder, detail=False)
    except FileNotFoundError:
        return {}
    return {posixpath.basename(path.rstrip("/")): path for path in paths}


def recorded_keys(plan_location: str) -> dict[str, str]:
    """The shard keys in a staging folder's plan file; none when it is absent or from an older format.

    An unreadable plan file also gives none: then every shard is rebuilt, which is always correct.
    """
    try:
        with fsspec.open(plan_location, "rb") as stream:
            plan = json.loads(stream.read())
    except (OSError, ValueError):
        return {}
    keys = plan.get("shard_keys") if isinstance(plan, dict) else None
    return keys if isinstance(keys, dict) else {}


def kept_shard_entry(staging: str, shard: ShardSpec) -> ShardEntry:
    """The manifest entry of a shard kept from an interrupted run, read back from its file."""
    location = posixpath.join(staging, shard.name)
    file_digest, samples = shard_digests(location)
    planned = [sample.key for sample in shard.samples]
    if [key for key, _ in samples] != planned:
        raise DataFormatError(location, f"holds samples {[key for key, _ in samples][:3]}..., the "
                                        f"plan has {planned[:3]}...")
    return ShardEntry(shard.name, len(samples), file_digest, tuple(samples))


def write_manifest(staging: str, shards: list[ShardSpec], dataset: str, entries: dict[str, ShardEntry]) -> None:
    """The manifest of the shards in ``staging``: one row per sample, and each shard's count and SHA-256."""
    rows = [(shard.name, sample) for shard in shards for sample in shard.samples]
    columns = {
        "shard": [name for name, _ in rows],
        "key": [s.key for _, s in rows],
        "dataset": [dataset] * len(rows),
        "sequence": [s.sequence for _, s in rows],
        "group": [s.group for _, s in rows],
        "frame": [s.frame for _, s in rows],
        "split": [s.split for _, s in rows],
        "sha256": [digest for shard in shards for _, digest in entries[shard.name].sample_sha256],
    }
    manifest = manifest_bytes(columns, [entries[shard.name] for shard in shards])
    write_bytes(posixpath.join(staging, MANIFEST), manifest)


# ------------------------------------------------------------------------------------------- shard writing
_WORKER_SEQUENCES: dict[str, Sequence] = {}


class ShardProgress:
    """What the driver tells a person while shards are written: shards done, frames per second, time left.

    A line at most every ``interval`` seconds as shards complete, and one when the last is done. Shards hold
    equal numbers of samples, so the time left is the pace so far times the shards still to write.
    """

    def __init__(
        self,
        dataset: str,
        total: int,
        kept: int,
        interval: float = PROGRESS_INTERVAL_S,
        clock: Callable[[], float] = time.perf_counter,
        write: Callable[[str], Any] = lambda line: print(line, flush=True),
    ) -> None:
        self.dataset, self.total, self.kept, self.interval = dataset, total, kept, interval
        self.clock, self.write = clock, write
        self.started = self.last_line = clock()
        self.done = self.frames = 0

    def shard_done(self, result: ShardResult) -> None:
        self.done += 1
        self.frames += result.frames_decoded
        now = self.clock()
        if self.done < self.total and now - self.last_line < self.interval:
            return
        self.last_line = now
        elapsed = max(now - self.started, 1e-9)
        left = self.total - self.done
        when = (f"~{format_duration(elapsed / self.done * left)} left" if left
                else f"done in {format_duration(elapsed)}")
        self.write(f"[preprocess] {self.dataset}: {self.done}/{self.total} shards written ({self.kept} kept from "
                   f"an interrupted run) | {self.frames} frames, {self.frames / elapsed:.1f} frames/s | {when}")


def run_shard_writers(
    shards: list[ShardSpec],
    staging: str,
    settings: EncodeSettings,
    sequences: list[Sequence],
    load_sequences: Callable[[], list[Sequence]],
    workers: int,
    progress: ShardProgress,
) -> list[ShardResult]:
    """Write ``shards`` into ``staging``, in this process (``workers <= 1``) or a process pool."""
    if workers <= 1 or len(shards) <= 1:
        by_name = {s.name: s for s in sequences}
        results = []
        with single_threaded_opencv():
            for shard in shards:
                results.append(write_shard(shard, staging, settings, by_name))
                progress.shard_done(results[-1])
        return results
    with ProcessPoolExecutor(
        max_workers=min(workers, len(shards)),
        mp_context=pool_context(),
        initializer=_init_worker,
        initargs=(load_sequences,),
    ) as pool:
        futures = [pool.submit(_write_shard_in_worker, shard, staging, settings) for shard in shards]
        results = []
        try:
            for future in as_completed(futures):
                results.append(future.result())
                progress.shard_done(results[-1])
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            raise
        return results


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


def _write_shard_in_worker(shard: ShardSpec, staging: str, settings: EncodeSettings) -> ShardResult:
    return write_shard(shard, staging, settings, _WORKER_SEQUENCES)


def run_shard_tasks_on_ray(
    shards: list[ShardSpec],
    staging: str,
    settings: EncodeSettings,
    sequences: list[Sequence],
    cluster: RayConfig,
    progress: ShardProgress,
) -> list[ShardResult]:
    """Write ``shards`` into ``staging`` as Ray tasks, one per shard, on the cluster of ``cluster``.

    Each task gets its shard's plan, the settings and the sequences it reads (put into the object store once
    each, and only while a queued shard still needs them), writes the shard and returns its
    :class:`ShardResult`. A task's error is raised here as the task raised it (a damaged frame's
    :class:`DataFormatError` names the file) once the remaining tasks are cancelled and have ended. Ray is
    shut down again only if this call started it (or joined the cluster).
    """
    import ray

    if not shards:
        return []
    joined = connect_ray(cluster)
    try:
        results = _shard_tasks(shards, staging, settings, {s.name: s for s in sequences}, progress)
    finally:
        if joined:
            ray.shutdown()
    check_shards_arrived(staging, results)
    return results


def check_shards_arrived(staging: str, results: list[ShardResult]) -> None:
    """Every shard a task wrote must be in ``staging`` as this process sees it.

    A local output folder that is not shared with the other nodes gets their shards written to their own
    disks; without this check the manifest would list shards that are not there.
    """
    fs, folder = fsspec.core.url_to_fs(staging)
    missing = sorted({r.entry.name for r in results} - set(folder_entries(fs, folder)))
    if missing:
        raise DataFormatError(staging, f"shards {missing[:3]}... ({len(missing)} in all) written by Ray tasks are "
                                       f"not here: preprocess.out must be a shared filesystem or an fsspec URL "
                                       f"that every node of the cluster writes to")


def _shard_tasks(
    shards: list[ShardSpec],
    staging: str,
    settings: EncodeSettings,
    sequences: dict[str, Sequence],
    progress: ShardProgress,
) -> list[ShardResult]:
    import ray

    task = ray.remote(num_cpus=1)(_write_shard_task)
    window = RAY_TASKS_PER_CPU * max(1, int(ray.cluster_resources().get("CPU", 1)))
    last_use = {name: index for index, shard in enumerate(shards) for name in shard_sequences(shard)}
    stored: dict[str, Any] = {}  # sequence name -> object ref, while a shard not yet submitted reads it
    pending: list = []
    results = []
    try:
        for index, shard in enumerate(shards):
            if len(pending) >= window:
                results.append(_next_task_result(pending, progress))
            names = shard_sequences(shard)
            for name in names:
                if name not in stored:
                    stored[name] = ray.put(sequences[name])
            pending.append(task.remote(shard, staging, settings, *(stored[name] for name in names)))
            for name in names:
                if last_use[name] == index:
                    del stored[name]  # the queued tasks hold their own references
        while pending:
            results.append(_next_task_result(pending, progress))
    except BaseException:
        stop_tasks(pending)
        raise
    return results


def stop_tasks(pending: list) -> None:
    """Cancel the tasks of ``pending`` and wait until each has ended.

    A running task is interrupted (its atomic write then removes its temporary) or finishes its shard; either
    way no task of this run still writes into the staging folder once the error reaches the caller, so a
    rerun that starts at once never meets a file being written.
    """
    import ray

    for ref in pending:
        ray.cancel(ref)
    if pending:
        print(f"[preprocess] stopping {len(pending)} shard tasks after the error", flush=True)
        ray.wait(pending, num_returns=len(pending))


def shard_sequences(shard: ShardSpec) -> list[str]:
    """Names of the sequences a shard's samples come from, in order."""
    return list(dict.fromkeys(spec.sequence for spec in shard.samples))


def _next_task_result(pending: list, progress: ShardProgress) -> ShardResult:
    """The result of the next task to finish (removed from ``pending``); its error raised as the task raised it."""
    import ray

    [done], _ = ray.wait(pending, num_returns=1)
    pending.remove(done)
    try:
        result = ray.get(done)
    except ray.exceptions.RayTaskError as error:
        if isinstance(error.cause, Exception):
            raise error.cause from error
        raise
    progress.shard_done(result)
    return result


def _write_shard_task(
    shard: ShardSpec, staging: str, settings: EncodeSettings, *sequences: Sequence
) -> ShardResult:
    """A Ray task: one shard, written to ``staging`` (a path every node sees, or an fsspec URL)."""
    with single_threaded_opencv():
        return write_shard(shard, staging, settings, {s.name: s for s in sequences})


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
    files[META_MEMBER] = json.dumps(sample_meta(spec, sequence, positions, settings), sort_keys=True).encode()
    return files, out_of_range


def sample_meta(
    spec: SampleSpec, sequence: Sequence, positions: dict[str, int], settings: EncodeSettings
) -> dict:
    names = IMAGE_NAMES
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

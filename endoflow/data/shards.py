"""Preprocessing: dataset sequences -> WebDataset shards of target frames with their neighbours.

Output of :func:`preprocess_dataset`: a shard folder in the format that :mod:`endoflow.data.shard_format`
defines (member names, depth encoding, the manifest with every shard's sample count and SHA-256). This module
runs the steps, each in its own module: the plan (:mod:`~endoflow.data.shard_plan`: samples, shards, resume
keys), the staging folder and manifest (:mod:`~endoflow.data.shard_staging`: atomic, resumable runs), an engine
(:mod:`~endoflow.data.shard_engines`: local processes or Ray tasks) writing each shard
(:mod:`~endoflow.data.shard_writer`) from frames encoded by :mod:`~endoflow.data.frame_encoding`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from endoflow.config import Params
from endoflow.data.base import DATASETS, Sequence
from endoflow.data.registry import open_reader
from endoflow.data.shard_engines import ShardProgress, run_shard_tasks_on_ray, run_shard_writers
from endoflow.data.shard_format import SPLITS
from endoflow.data.shard_plan import encode_settings, plan_shards, samples_without_pose, shard_keys
from endoflow.data.shard_staging import OutputFolder, kept_shard_entry, prepare_staging, write_manifest
from endoflow.locations import absolute_location


@dataclass(frozen=True)
class ReaderSequences:
    """Picklable ``() -> list[Sequence]`` opening a dataset through the registry (run in each worker)."""

    root: str
    dataset: str
    params: Params

    def __call__(self) -> list[Sequence]:
        return open_reader(self.root, self.dataset, self.params).sequences()


def preprocess_dataset(dataset: str, params: Params, out_dir: str | Path) -> dict:
    """Write the shards and manifest of ``dataset`` (a name of :data:`~endoflow.config.DATASETS`) into ``out_dir``.

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

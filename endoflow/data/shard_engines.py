"""The two engines that write planned shards (``preprocess.engine``), and the progress lines they report.

``local`` writes shards in this process or a pool of ``preprocess.workers`` processes; ``ray`` runs one Ray task
per shard on the cluster at ``ray.address`` (a local Ray when it is null,
:func:`endoflow.ray_runtime.connect_ray`), each task writing its shard to the output location and returning its
typed :class:`~endoflow.data.shard_writer.ShardResult`. Shards of equal size make equal tasks, however long a
sequence is. Both write each shard with :func:`~endoflow.data.shard_writer.write_shard`, so both give the same
bytes; the driver (:mod:`endoflow.data.shards`) plans, keeps the resume keys and writes the manifest.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from pathlib import PurePosixPath
from typing import Any, Callable, Iterator

import cv2
import fsspec

from endoflow.config import RayConfig
from endoflow.data.base import Sequence
from endoflow.data.shard_plan import EncodeSettings, ShardSpec
from endoflow.data.shard_staging import folder_entries
from endoflow.data.shard_writer import ShardResult, write_shard
from endoflow.errors import DataFormatError
from endoflow.io import TEMPORARY_MARK
from endoflow.progress import Progress
from endoflow.ray_runtime import connect_ray

# Seconds between progress lines while shards are written (the last shard always gets one).
PROGRESS_INTERVAL_S = 10.0
# Ray tasks queued per cluster CPU: enough that no CPU waits for the driver, few enough that the object
# store holds only the sequences of shards in flight (SceneNet has millions of frames).
RAY_TASKS_PER_CPU = 2
# A pool worker's sequences by name, loaded once when the worker starts (_init_worker).
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
        self.dataset, self.kept, self.write = dataset, kept, write
        self.progress = Progress(total, "shards", interval, clock)
        self.done = self.frames = 0

    def shard_done(self, result: ShardResult) -> None:
        self.done += 1
        self.frames += result.frames_decoded
        if not self.progress.due(self.done):
            return
        frame_rate = self.progress.rate(self.frames)
        frames = f"{self.frames} frames" + (f", {frame_rate:.1f} frames/s" if frame_rate is not None else "")
        self.write(f"[preprocess] {self.dataset}: {self.progress.update(self.done)} | {frames} "
                   f"({self.kept} shards kept from an interrupted run)")


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

    ``fork`` where it is safe (Linux, no other Python thread, and no native thread started in this process since
    this module was imported; numpy's BLAS pool, started on import, prepares for a fork): workers start at once with
    everything already imported, which matters when the work takes seconds. Otherwise a fork server (a clean
    process, so threads of Ray, torch or FFmpeg's decoders are never inherited holding a lock) with this module
    preloaded, or ``spawn`` where there is no fork server.
    """
    methods = multiprocessing.get_all_start_methods()
    quiet = threading.active_count() == 1 and native_thread_count() <= THREADS_AT_IMPORT
    if sys.platform.startswith("linux") and quiet:
        return multiprocessing.get_context("fork")
    if "forkserver" in methods:
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload([__name__])
        return context
    return multiprocessing.get_context("spawn")


def native_thread_count() -> int:
    """Threads of this process, those started by libraries outside Python (FFmpeg, OpenMP) included (Linux)."""
    return len(os.listdir("/proc/self/task"))


THREADS_AT_IMPORT = native_thread_count() if sys.platform.startswith("linux") else 0


def _init_worker(load_sequences: Callable[[], list[Sequence]]) -> None:
    # Parallelism comes from the processes; OpenCV's own threads would only compete with them.
    cv2.setNumThreads(1)
    _WORKER_SEQUENCES.clear()
    _WORKER_SEQUENCES.update({s.name: s for s in load_sequences()})


def _write_shard_in_worker(shard: ShardSpec, staging: str, settings: EncodeSettings) -> ShardResult:
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
        remove_temporaries(staging)
        raise
    return results


def remove_temporaries(staging: str) -> None:
    """Remove the temporaries of shards whose task was stopped mid-write (a cancel's interrupt can land between a
    temporary's creation and the block that removes it); only once every task of the run has ended."""
    fs, folder = fsspec.core.url_to_fs(staging)
    if fs.exists(folder):
        for path in fs.ls(folder, detail=False):
            if TEMPORARY_MARK in PurePosixPath(path).name:
                fs.rm(path)


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

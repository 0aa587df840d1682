"""Work beside the model's: frames read ahead in one thread (decoded side by side in a few more where the input
allows), per-frame outputs written behind in another, each frame's depth PNGs encoded side by side in a few more.

A frame's decoding (PyAV, OpenCV's PNG reader and resize) and its outputs' encoding (PNG, H.264, the recording)
release the GIL, so on two cores they overlap the model and the fusion of the frame in hand instead of adding
to it. Torch work stays in the calling thread: a second thread's torch ops would start a second pool of torch
threads, and two pools on two cores wait on each other.
"""

from __future__ import annotations

import os
import queue
import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

Item = TypeVar("Item")
READ_AHEAD = 4  # frames decoded ahead of the model: enough to smooth a slow decode, few enough for 1080p memory
WRITE_BEHIND = 4  # frames whose outputs may wait to be written before the next frame waits for them
_POLL_SECONDS = 0.1
# At 480 px a frame's two depth PNGs took 24 ms of one thread on the H100 machine, more than its GPU took for the
# networks and the fusion of the frame (15 ms): one encoding thread for every four cores, at most four (Encoders).
# Decoding is the same on the way in (a 480 px dataset frame's colour and depth PNGs kept its reading thread 80 %
# busy there): as many decoding threads (decoded_ahead).
CORES_PER_ENCODER = 4
MOST_ENCODERS = 4


def read_ahead(items: Iterable[Item], count: int = READ_AHEAD) -> Iterator[Item]:
    """``items`` as they are, produced by a background thread up to ``count`` ahead of the consumer.

    An error raised while producing an item is raised here, in its place; leaving the loop early (an error in
    the consumer, a ``break``) stops the thread before this generator closes."""
    slots: queue.Queue = queue.Queue(maxsize=count)
    stopped = threading.Event()

    def offer(entry: tuple) -> bool:
        while not stopped.is_set():
            try:
                slots.put(entry, timeout=_POLL_SECONDS)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not offer(("item", item)):
                    return
            offer(("end", None))
        except BaseException as error:  # handed to the consumer, which raises it
            offer(("error", error))

    thread = threading.Thread(target=produce, name="read-ahead", daemon=True)
    thread.start()
    try:
        while True:
            kind, value = slots.get()
            if kind == "end":
                return
            if kind == "error":
                raise value
            yield value
    finally:
        stopped.set()
        thread.join()


def decoded_ahead(reads: Iterable[Callable[[], Item]], count: int = READ_AHEAD, workers: int = 0) -> Iterator[Item]:
    """What each of ``reads`` returns, in order, made up to ``count`` ahead of the consumer: by ``workers`` threads
    side by side (calls that may run in any order, such as the decoding of a folder's images), or, for
    ``workers`` below 2, one after another in :func:`read_ahead`'s thread. An error is raised in its place, as
    :func:`read_ahead` raises it; leaving the loop early stops the threads before this generator closes (a
    decoding already running finishes)."""
    if workers < 2:
        yield from read_ahead((read() for read in reads), count)
        return
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="decode")
    futures = read_ahead((pool.submit(read) for read in reads), count)
    try:
        for future in futures:
            yield future.result()
    finally:  # no more submitted, then those not started dropped and the running ones waited for
        futures.close()
        pool.shutdown(wait=True, cancel_futures=True)


def side_threads(cores: int | None = None) -> int:
    """Threads for work beside the model's that may run side by side (encoding, decoding): one for every
    :data:`CORES_PER_ENCODER` of ``cores`` (default: the cores this process may run on), at most
    :data:`MOST_ENCODERS`; 0 where that makes fewer than two (one more thread only adds a hand-off)."""
    cores = cores if cores is not None else len(os.sched_getaffinity(0))
    threads = min(MOST_ENCODERS, cores // CORES_PER_ENCODER)
    return threads if threads >= 2 else 0


class WriteBehind:
    """Calls run in submission order on one background thread, at most :data:`WRITE_BEHIND` waiting.

    Use as a context manager: leaving it waits for every call submitted (or, on an error, cancels those not
    started and waits for the one running), so nothing is written after the caller has moved on. The first error
    of a call is raised by the next :meth:`submit` that waits for it or by leaving the block; calls already waiting
    behind the failed one may still run (their outputs go to a folder the error then discards)."""

    def __init__(self, waiting: int = WRITE_BEHIND) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="write-behind")
        self._pending: deque[Future] = deque()
        self._waiting = waiting

    def submit(self, call: Callable[..., object], *args: object) -> None:
        while self._pending and (self._pending[0].done() or len(self._pending) >= self._waiting):
            self._pending.popleft().result()  # re-raises a failed write here
        self._pending.append(self._pool.submit(call, *args))

    def __enter__(self) -> "WriteBehind":
        return self

    def __exit__(self, error_type, error, traceback) -> None:
        if error_type is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            return
        try:
            while self._pending:
                self._pending.popleft().result()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)


class Deferred:
    """A call made by the thread that asks for its :meth:`result`, which must ask once: a second ask calls
    again."""

    def __init__(self, call: Callable[..., Item], *args: object) -> None:
        self._call, self._args = call, args

    def result(self) -> Item:
        return self._call(*self._args)


class Encoders:
    """Threads for work whose order does not matter (each frame's PNGs, each to its own file): :func:`side_threads`
    of ``cores``. Where that makes none (``workers`` 0), :meth:`submit` defers the call to the thread that asks for
    its result (the writer's): a pool of one only added a hand-off, which on 2 busy cores took a 64 px frame's rate
    down by about two fifths. Use as a context manager: leaving it waits for every call started (on an error, those
    not started are dropped)."""

    def __init__(self, cores: int | None = None) -> None:
        self.workers = side_threads(cores)
        self._pool = (ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="encode")
                      if self.workers else None)

    def submit(self, call: Callable[..., Item], *args: object) -> Future | Deferred:
        return self._pool.submit(call, *args) if self._pool is not None else Deferred(call, *args)

    def __enter__(self) -> "Encoders":
        return self

    def __exit__(self, error_type, error, traceback) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=error_type is not None)

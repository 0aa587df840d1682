"""What long-running work tells a person: how far it is, its pace and the time left, in one line format.

:class:`Progress` is the one place these lines are built (preprocessing, pretraining, training, reconstruction).
"""

from __future__ import annotations

import logging
import os
import time
from contextlib import contextmanager
from typing import Callable, Iterator, Optional


def format_duration(seconds: float) -> str:
    """``1h05m`` from an hour up, else ``4m10s`` (negative durations read as zero)."""
    seconds = int(max(seconds, 0))
    hours, rest = divmod(seconds, 3600)
    minutes, seconds = divmod(rest, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{seconds:02d}s"


class Progress:
    """Work of ``total`` units (``None``: not known in advance) timed from construction.

    :meth:`update` gives ``12/40 frames | 3.0 frames/s | ~0m09s left`` (``done in 0m13s`` once all is done);
    :meth:`pace` the same without the count, for lines that say how far they are in their own words. The time
    left is the units still to do at the pace so far, unless the caller knows better (``seconds_left``).
    :meth:`due` spaces the lines at least ``interval`` seconds apart, the last one always shown.
    """

    def __init__(self, total: Optional[float], unit: str, interval: float = 0.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.total, self.unit, self.interval, self.clock = total, unit, interval, clock
        self.started = self.last_line = clock()

    def elapsed(self) -> float:
        return self.clock() - self.started

    def rate(self, amount: float) -> Optional[float]:
        """``amount`` per second so far; ``None`` before any time has passed."""
        elapsed = self.elapsed()
        return amount / elapsed if elapsed > 0 else None

    def due(self, done: float) -> bool:
        """Whether a line is due (``interval`` passed since the last, or all done); a due line counts as shown."""
        now = self.clock()
        if not self.finished(done) and now - self.last_line < self.interval:
            return False
        self.last_line = now
        return True

    def finished(self, done: float) -> bool:
        return self.total is not None and done >= self.total

    def pace(self, done: float, seconds_left: Optional[float] = None) -> str:
        """``3.0 frames/s | ~0m09s left``; the parts not known yet (no time passed, no total) are left out."""
        rate = self.rate(done)
        if seconds_left is None and rate and self.total is not None:
            seconds_left = (self.total - done) / rate
        parts = [f"{rate:.1f} {self.unit}/s" if rate is not None else "",
                 f"~{format_duration(seconds_left)} left" if seconds_left is not None else ""]
        return " | ".join(part for part in parts if part) or "just started"

    def update(self, done: float, seconds_left: Optional[float] = None) -> str:
        """``12/40 frames | 3.0 frames/s | ~0m09s left``, or ``... | done in 0m13s`` once ``done`` reaches the total."""
        count = f"{done}/{self.total} {self.unit}" if self.total is not None else f"{done} {self.unit}"
        if not self.finished(done):
            return f"{count} | {self.pace(done, seconds_left)}"
        rate = self.rate(done)
        speed = f"{rate:.1f} {self.unit}/s | " if rate is not None else ""
        return f"{count} | {speed}done in {format_duration(self.elapsed())}"


@contextmanager
def environment_default(name: str, value: str) -> Iterator[None]:
    """Within: the environment variable ``name`` reads ``value`` unless the user set it: how a library that reads
    its settings from the environment is told to print less. Removed again after."""
    if name in os.environ:
        yield
        return
    os.environ[name] = value
    try:
        yield
    finally:
        os.environ.pop(name, None)


@contextmanager
def logger_quieted(name: str, level: int = logging.WARNING) -> Iterator[None]:
    """Within: the logger ``name`` passes only records at ``level`` and above: how a library's notes that tell a
    user nothing to act on are kept off the terminal. Its own level is restored after."""
    logger = logging.getLogger(name)
    previous = logger.level
    logger.setLevel(max(level, logger.getEffectiveLevel()))
    try:
        yield
    finally:
        logger.setLevel(previous)

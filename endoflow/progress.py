"""What long-running work tells a person: durations written the way a progress line shows them."""

from __future__ import annotations


def format_duration(seconds: float) -> str:
    """``1h05m`` from an hour up, else ``4m10s`` (negative durations read as zero)."""
    seconds = int(max(seconds, 0))
    hours, rest = divmod(seconds, 3600)
    minutes, seconds = divmod(rest, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{seconds:02d}s"

"""The one progress line: how far, the pace and the time left, timed by a clock the test moves."""

from __future__ import annotations

from endoflow.progress import Progress, format_duration


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_line_gives_the_count_the_pace_and_the_time_left_at_that_pace() -> None:
    clock = FakeClock()
    progress = Progress(40, "frames", clock=clock)
    clock.now += 4.0
    assert progress.update(12) == "12/40 frames | 3.0 frames/s | ~0m09s left"
    assert progress.pace(12) == "3.0 frames/s | ~0m09s left"


def test_a_caller_that_knows_the_time_left_better_gives_it() -> None:
    clock = FakeClock()
    progress = Progress(10, "steps", clock=clock)
    clock.now += 2.0
    assert progress.pace(4, seconds_left=95.0) == "2.0 steps/s | ~1m35s left"


def test_before_any_time_has_passed_no_pace_or_time_left_is_made_up() -> None:
    progress = Progress(10, "frames", clock=FakeClock())
    assert progress.rate(3) is None
    assert progress.update(3) == "3/10 frames | just started"


def test_the_last_line_says_how_long_it_all_took() -> None:
    clock = FakeClock()
    progress = Progress(6, "shards", clock=clock)
    clock.now += 75.0
    assert progress.update(6) == "6/6 shards | 0.1 shards/s | done in 1m15s"


def test_without_a_total_the_line_has_the_count_and_the_pace_only() -> None:
    clock = FakeClock()
    progress = Progress(None, "frames", clock=clock)
    clock.now += 2.0
    assert progress.update(50) == "50 frames | 25.0 frames/s"
    assert not progress.finished(50)


def test_lines_are_due_once_per_interval_and_at_the_end() -> None:
    clock = FakeClock()
    progress = Progress(5, "shards", interval=10.0, clock=clock)
    due = []
    for done, at in enumerate((3.0, 11.0, 15.0, 20.0, 22.0), start=1):
        clock.now = 100.0 + at
        due.append(progress.due(done))
    assert due == [False, True, False, False, True]  # 11 s after the start; the last shard


def test_durations_read_in_minutes_and_seconds_or_hours_and_minutes() -> None:
    assert format_duration(250.9) == "4m10s"
    assert format_duration(3900) == "1h05m"
    assert format_duration(-3) == "0m00s"

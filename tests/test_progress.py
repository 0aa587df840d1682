"""The one progress line: how far, the pace and the time left, timed by a clock the test moves; and how a
library is told to print less, for a block only."""

from __future__ import annotations

import logging
import os

import pytest

from endoflow.progress import Progress, environment_default, format_duration, logger_quieted


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


def test_a_quieted_logger_drops_notes_below_the_level_within_the_block_only(caplog) -> None:
    logger = logging.getLogger("some.library")
    logger.setLevel(logging.INFO)
    with caplog.at_level(logging.INFO, logger="some.library"), logger_quieted("some.library"):
        logger.info("a note")
        logger.warning("a warning")
    assert [r.getMessage() for r in caplog.records] == ["a warning"]
    assert logger.level == logging.INFO


def test_quieting_never_lets_more_through_than_the_logger_already_did() -> None:
    logger = logging.getLogger("some.quiet.library")
    logger.setLevel(logging.ERROR)
    with logger_quieted("some.quiet.library", logging.WARNING):
        assert logger.getEffectiveLevel() == logging.ERROR
    assert logger.level == logging.ERROR


def test_an_environment_default_yields_to_the_users_setting(monkeypatch) -> None:
    monkeypatch.delenv("ENDOFLOW_TEST_SETTING", raising=False)
    with environment_default("ENDOFLOW_TEST_SETTING", "false"):
        assert os.environ["ENDOFLOW_TEST_SETTING"] == "false"
    assert "ENDOFLOW_TEST_SETTING" not in os.environ
    monkeypatch.setenv("ENDOFLOW_TEST_SETTING", "true")
    with environment_default("ENDOFLOW_TEST_SETTING", "false"):
        assert os.environ["ENDOFLOW_TEST_SETTING"] == "true"
    assert os.environ["ENDOFLOW_TEST_SETTING"] == "true"


def test_a_quieted_logger_is_restored_when_the_block_raises() -> None:
    logger = logging.getLogger("some.raising.library")
    logger.setLevel(logging.DEBUG)
    with pytest.raises(RuntimeError), logger_quieted("some.raising.library"):
        raise RuntimeError("inside")
    assert logger.level == logging.DEBUG

"""Reading ahead and writing behind (endoflow/reconstruction/streams.py): the same items in the same order as
without the threads, errors raised where they belong, and nothing left running after an early stop."""

from __future__ import annotations

import threading
import time

import pytest

from endoflow.reconstruction.streams import Encoders, WriteBehind, decoded_ahead, read_ahead, side_threads


def test_read_ahead_yields_every_item_in_order() -> None:
    assert list(read_ahead(iter(range(100)), count=3)) == list(range(100))


def test_an_error_while_reading_is_raised_in_its_place_after_the_items_before_it() -> None:
    def items():
        yield from range(5)
        raise ValueError("frame 5 is damaged")

    seen = []
    with pytest.raises(ValueError, match="frame 5 is damaged"):
        for item in read_ahead(items()):
            seen.append(item)
    assert seen == list(range(5))


def test_stopping_early_stops_the_reading_thread() -> None:
    produced = []

    def endless():
        while True:
            produced.append(len(produced))
            yield produced[-1]

    before = set(threading.enumerate())
    items = read_ahead(endless(), count=2)
    for item in items:
        if item == 3:
            break
    items.close()  # what reconstruct's closing() does on leaving the loop
    count = len(produced)
    time.sleep(0.3)
    assert len(produced) == count <= 3 + 2 + 2  # the consumer's items, the queue's and the one being offered
    assert not [t for t in set(threading.enumerate()) - before if t.name == "read-ahead"]


def slow_reads(count: int, made: list[int]) -> list:
    """Calls that return their number after a wait that shrinks along the list (from 60 ms): side by side, later
    ones finish first."""
    def read(number: int) -> int:
        time.sleep(0.06 * (count - number) / count)
        made.append(number)
        return number
    return [lambda number=number: read(number) for number in range(count)]


@pytest.mark.parametrize("workers", [0, 1, 3])
def test_decoding_side_by_side_yields_every_result_in_the_order_of_the_reads(workers: int) -> None:
    made: list[int] = []
    assert list(decoded_ahead(slow_reads(30, made), count=4, workers=workers)) == list(range(30))
    assert sorted(made) == list(range(30))


def test_reads_run_side_by_side_in_several_threads() -> None:
    together = threading.Barrier(3, timeout=10)  # three reads at a time, or it breaks
    threads = set()

    def read() -> None:
        threads.add(threading.current_thread().name)
        together.wait()

    list(decoded_ahead([read] * 12, count=4, workers=3))
    assert len(threads) == 3 and all(name.startswith("decode") for name in threads)


def test_a_failed_read_is_raised_in_its_place_after_the_results_before_it() -> None:
    def damaged() -> int:
        raise ValueError("frame 5 is damaged")

    reads = slow_reads(10, [])
    reads[5] = damaged
    seen = []
    with pytest.raises(ValueError, match="frame 5 is damaged"):
        for item in decoded_ahead(reads, count=3, workers=3):
            seen.append(item)
    assert seen == list(range(5))


def test_stopping_early_stops_the_decoding_threads_and_reads_no_further() -> None:
    made: list[int] = []
    before = set(threading.enumerate())
    results = decoded_ahead(slow_reads(1000, made), count=2, workers=3)
    for item in results:
        if item == 3:
            break
    results.close()
    count = len(made)
    time.sleep(0.3)
    assert len(made) == count < 20  # the consumer's, the queue's and those running when it stopped
    assert not [t for t in set(threading.enumerate()) - before if t.name.startswith(("decode", "read-ahead"))]


def test_writes_run_in_submission_order_and_all_finish_before_the_block_is_left() -> None:
    written = []
    with WriteBehind(waiting=2) as writes:
        for index in range(20):
            writes.submit(lambda i: (time.sleep(0.001), written.append(i)), index)
    assert written == list(range(20))


def test_a_failed_write_is_raised_by_the_submit_that_waits_for_it_and_no_write_after_that_runs() -> None:
    written = []

    def write(index: int) -> None:
        if index == 2:
            raise OSError("disk full")
        written.append(index)

    with pytest.raises(OSError, match="disk full"):
        with WriteBehind(waiting=1) as writes:
            for index in range(10):
                writes.submit(write, index)
    assert written == [0, 1]


def test_leaving_on_an_error_cancels_the_writes_not_started() -> None:
    started = []
    with pytest.raises(KeyboardInterrupt):
        with WriteBehind(waiting=50) as writes:
            for index in range(20):
                writes.submit(lambda i: (started.append(i), time.sleep(0.05)), index)
            raise KeyboardInterrupt
    assert len(started) < 20


@pytest.mark.parametrize("cores, threads", [(1, 0), (4, 0), (7, 0), (8, 2), (16, 4), (64, 4)])
def test_one_encoding_or_decoding_thread_for_every_four_cores_at_most_four_and_none_below_two(cores, threads) -> None:
    with Encoders(cores) as encoders:
        assert encoders.workers == side_threads(cores) == threads


@pytest.mark.parametrize("cores", [2, 16])
def test_an_encoding_runs_beside_its_caller_where_two_threads_are_offered_else_in_the_thread_that_asks(cores) -> None:
    with Encoders(cores) as encoders:
        done = encoders.submit(lambda x: (x + 1, threading.current_thread()), 1)
        asked_from = []
        asker = threading.Thread(target=lambda: asked_from.append(done.result()))
        asker.start()
        asker.join()
    value, ran_in = asked_from[0]
    assert value == 2
    assert (ran_in is asker) == (cores < 8)


def test_leaving_the_encoders_waits_for_every_encoding() -> None:
    finished = []
    with Encoders(16) as encoders:
        for i in range(6):
            encoders.submit(lambda i=i: (time.sleep(0.01), finished.append(i)))
    assert sorted(finished) == list(range(6))

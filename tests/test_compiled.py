"""How loops are compiled: cached on disk where numba can write a cache, compiled in each process where it cannot;
a part compiled into the loops that call it."""

from __future__ import annotations

import numba
import pytest

from endoflow import compiled


def test_without_a_writable_cache_folder_the_loops_compile_in_each_process(monkeypatch: pytest.MonkeyPatch) -> None:
    asked: list[dict] = []
    njit = numba.njit

    def no_cache_folder(*functions, **options):  # what numba raises when no folder for its cache is writable
        if functions:  # numba's own use while it compiles (its typed containers, loaded on first use)
            return njit(*functions, **options)
        asked.append(options)
        if options.get("cache"):
            raise RuntimeError("cannot cache function 'double': no locator available for file 'compiled.py'")
        return njit(**options)

    def double(x):
        return 2 * x

    monkeypatch.setattr(numba, "njit", no_cache_folder)
    assert compiled.compiled_loop(double)(21) == 42
    assert asked == [{"cache": True, "nogil": True}, {"nogil": True}]


def test_a_compiled_part_runs_inside_the_loop_that_calls_it() -> None:
    @compiled.compiled_part
    def squared(x):
        return x * x

    def sum_of_squares(count):
        total = 0
        for value in range(count):
            total += squared(value)
        return total

    assert compiled.compiled_loop(sum_of_squares)(4) == 0 + 1 + 4 + 9

"""How the suite runs on several processes: the modules with slow end-to-end runs first, and idle threads that
sleep.

`make test` spreads the modules over three processes (pytest-xdist, a module to a process, in this order). A run of
several minutes started last would leave one process working alone at the end; started first, the short modules
fill the other processes meanwhile.
"""

from __future__ import annotations

import os

import pytest

if "PYTEST_XDIST_WORKER" in os.environ:
    # Several processes, each with torch's 2 OpenMP threads (and the stage processes they start), share 2 cores. An
    # idle OpenMP thread spins by default, taking the core from another process: two copies of a training test
    # took 138 s side by side against 55 s with sleeping threads (33 s alone). Read when torch loads, after this.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    slow_modules = {module_of(item) for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: module_of(item) not in slow_modules)  # a stable sort: otherwise as collected


def module_of(item: pytest.Item) -> str:
    return item.nodeid.split("::")[0]

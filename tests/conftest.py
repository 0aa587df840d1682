"""How the suite runs on several processes: the modules with slow end-to-end runs first, idle threads that sleep,
and a module's folders removed when it ends.

`make test` spreads the modules over three processes (pytest-xdist, a module to a process, in this order). A run of
several minutes started last would leave one process working alone at the end; started first, the short modules
fill the other processes meanwhile.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.module_temp import ModuleTemp

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


# The modules with a failed test or fixture in this process: their folders are kept, as pytest keeps a failed test's
# tmp_path (pyproject.toml: tmp_path_retention_policy), to look at after the run.
failed_modules: set[str] = set()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    report = yield
    if report.failed:
        failed_modules.add(module_of(item))
    return report


@pytest.fixture(scope="module")
def module_tmp(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> Iterator[ModuleTemp]:
    """Makes a folder for a module's fixtures, by name; they go when the module ends unless a test or a setup in it
    failed (an error in the last test's teardown is reported after they went).

    A run of the suite used to leave 8.7 GB under /tmp until its end (models of 100 MB, checkpoints of 430 MB, whole
    project clones), and CI's disk once ran out.
    """
    made: list[Path] = []

    def mktemp(name: str) -> Path:
        made.append(tmp_path_factory.mktemp(name))
        return made[-1]

    yield mktemp
    if request.node.nodeid not in failed_modules:
        for folder in made:
            shutil.rmtree(folder, ignore_errors=True)

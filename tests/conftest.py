"""The suite's order: the modules with slow end-to-end runs first.

`make test` spreads the modules over two processes (pytest-xdist, a module to a process, in this order). A run of
several minutes started last would leave one process working alone at the end; started first, the short modules
fill the other process meanwhile.
"""

from __future__ import annotations

import pytest


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    slow_modules = {module_of(item) for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: module_of(item) not in slow_modules)  # a stable sort: otherwise as collected


def module_of(item: pytest.Item) -> str:
    return item.nodeid.split("::")[0]

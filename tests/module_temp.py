"""The type of the `module_tmp` fixture (tests/conftest.py): it makes a folder for a module's fixtures by name."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

ModuleTemp = Callable[[str], Path]

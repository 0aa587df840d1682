"""The one place the benchmarks that compare versions of the code choose which ``endoflow`` a process imports."""

from __future__ import annotations

import os
from pathlib import Path


def environment_importing(tree: Path) -> dict[str, str]:
    """This process's environment with ``tree`` (a folder holding an ``endoflow`` package, e.g. ``git archive
    <commit> endoflow | tar -x -C tree``) first on ``PYTHONPATH``, so that a child process imports that version.

    Raises:
        SystemExit: naming the folder, where it holds no ``endoflow`` package.
    """
    package = tree / "endoflow" / "__init__.py"
    if not package.is_file():
        raise SystemExit(f"{tree}: no endoflow package there (expected {package})")
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")])}

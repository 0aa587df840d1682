"""Where inputs and outputs live: local paths (relative to the project root) or fsspec URLs.

Local paths are made absolute before they cross into a Ray worker (which runs in a session folder of its own);
URLs pass as they are. :func:`home_project` finds the project whose MLflow store and Ray checkpoints a run uses,
also from a DVC experiment's temporary copy. See docs/architecture.md, "Contracts and their homes".
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import fsspec


# DVC sets this for every stage it runs: the project root, and for an experiment run in a temporary copy, the root
# of the project the experiment was queued in
DVC_ROOT_ENV = "DVC_ROOT"


def home_project(project_root: str | Path) -> Path:
    """The project whose MLflow store and Ray checkpoints a run uses: the one DVC names in ``DVC_ROOT`` (for a
    queued experiment, the project rather than its temporary copy, which DVC deletes after), else
    ``project_root``."""
    return Path(os.environ.get(DVC_ROOT_ENV) or project_root).resolve()


def absolute_location(location: str, project_root: Path) -> str:
    """fsspec URLs unchanged; local paths made absolute against the project root."""
    if "://" in location:
        return location
    path = Path(location)
    return str(path if path.is_absolute() else (project_root / path).resolve())


def local_file(location: str) -> str:
    """A local path for ``location`` (a remote fsspec URL is copied into a temporary file once per call)."""
    if location.startswith("file://"):
        return fsspec.core.url_to_fs(location)[1]
    if "://" not in location:
        return location
    with fsspec.open(location, "rb") as remote:
        data = remote.read()
    local = Path(tempfile.mkdtemp(prefix="endoflow-")) / Path(location).name
    local.write_bytes(data)
    return str(local)

"""Where inputs and outputs live: local paths (relative to the project root) or fsspec URLs.

Ray workers run in their own session folders, so every local location crossing into a worker is made
absolute first; URLs (``s3://...``, ``file:///...``) reach every node of a cluster as they are.

What outlives a run (the MLflow store, Ray's checkpoints) belongs to the project a run was started in, which for
a DVC experiment run in a temporary copy (``dvc exp run --queue`` then ``dvc queue start``, or ``--temp``) is
not the folder the stage runs in: :func:`home_project` finds it.
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

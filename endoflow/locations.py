"""Where inputs and outputs live: local paths (relative to the project root) or fsspec URLs.

Ray workers run in their own session folders, so every local location crossing into a worker is made
absolute first; URLs (``s3://...``, ``file:///...``) reach every node of a cluster as they are.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import fsspec


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

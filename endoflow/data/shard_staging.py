"""Where a preprocessing run writes: the staging folder, its plan file of resume keys, the manifest, publishing.

Runs are atomic and resumable: everything is written into a staging folder (:class:`OutputFolder`) together
with a plan file holding each shard's key (:func:`endoflow.data.shard_plan.shard_keys`); each shard appears
whole under its name or not at all (:func:`endoflow.io.atomic_location`). A rerun keeps a finished shard only
if its key is unchanged and writes the rest, so a shard is never reused after an input it was built from
changed. The output is a local path or an fsspec URL. On a filesystem (a path, ``file://``, a shared mount) the
staging folder is ``.<out name>.partial/`` beside the output and only a complete result replaces the output, so
an interrupted run never leaves half shards there. An object store (``s3://``) has no rename: the shards are
written in place, the old manifest removed first and the new one written last, so a reader finds either no
manifest (and says to run the preprocess stage) or the complete new output.
"""

from __future__ import annotations

import json
import posixpath
from dataclasses import dataclass
from pathlib import Path

import fsspec
from fsspec.implementations.local import LocalFileSystem

from endoflow.data.shard_format import MANIFEST, ShardEntry, manifest_bytes, shard_digests
from endoflow.data.shard_plan import ShardSpec
from endoflow.errors import DataFormatError
from endoflow.io import files_only, replace_directory, write_bytes

PLAN_FILE = "plan.json"
SHARD_FOLDER = files_only("a shard folder (a manifest and .tar shards)", (MANIFEST, "*.tar"))


@dataclass(frozen=True)
class OutputFolder:
    """Where a run writes (``staging``, a path or an fsspec URL) and where its complete result goes (``final``).

    On a filesystem (a path or ``file://``, local or a shared mount) staging is ``.<name>.partial/`` beside
    the output, swapped in whole by :func:`endoflow.io.replace_directory`. An object store has no rename, so
    staging is the output itself: :func:`prepare_staging` removes the old manifest first, and
    :meth:`publish` leaves the manifest, written last, as the point where the new output is complete.
    """

    final: str
    staging: str

    @classmethod
    def of(cls, out: str) -> "OutputFolder":
        fs, path = fsspec.core.url_to_fs(out)
        if isinstance(fs, LocalFileSystem):
            final = Path(path)
            return cls(str(final), str(final.parent / f".{final.name}.partial"))
        url = out.rstrip("/")
        return cls(url, url)

    def publish(self) -> None:
        """The plan file removed; the staging folder put in place of the output unless it is the output."""
        fs, path = fsspec.core.url_to_fs(posixpath.join(self.staging, PLAN_FILE))
        fs.rm(path)
        if self.staging != self.final:
            replace_directory(self.staging, self.final, SHARD_FOLDER)


def prepare_staging(staging: str, keys: dict[str, str]) -> set[str]:
    """Make ``staging`` ready for a plan whose shards have ``keys``; returns the names of shards kept.

    A finished shard is kept only when the key recorded for it in the staging folder's plan file equals
    its key now. Everything else (stale shards, temporaries, leftovers of another plan) is removed before
    the new keys are recorded, so a recorded key always describes the shard file of that name, or one not
    written yet. A manifest goes first: where staging is the output itself (an object store), readers then
    never pair it with shards that are going away.
    """
    fs, folder = fsspec.core.url_to_fs(staging)
    fs.makedirs(folder, exist_ok=True)
    recorded = recorded_keys(posixpath.join(staging, PLAN_FILE))
    present = folder_entries(fs, folder)
    kept = {name for name, key in keys.items() if recorded.get(name) == key and name in present
            and fs.isfile(present[name])}
    for name in sorted(present, key=lambda name: name != MANIFEST):
        if name not in kept and name != PLAN_FILE:
            fs.rm(present[name], recursive=True)
    plan = json.dumps({"shard_keys": keys}, indent=1, sort_keys=True).encode()
    write_bytes(posixpath.join(staging, PLAN_FILE), plan)
    return kept


def folder_entries(fs: fsspec.AbstractFileSystem, folder: str) -> dict[str, str]:
    """Name -> path of what ``folder`` holds; nothing when it does not exist (an object store's empty prefix)."""
    try:
        paths = fs.ls(folder, detail=False)
    except FileNotFoundError:
        return {}
    return {posixpath.basename(path.rstrip("/")): path for path in paths}


def recorded_keys(plan_location: str) -> dict[str, str]:
    """The shard keys in a staging folder's plan file; none when it is absent or from an older format.

    An unreadable plan file also gives none: then every shard is rebuilt, which is always correct.
    """
    try:
        with fsspec.open(plan_location, "rb") as stream:
            plan = json.loads(stream.read())
    except (OSError, ValueError):
        return {}
    keys = plan.get("shard_keys") if isinstance(plan, dict) else None
    return keys if isinstance(keys, dict) else {}


def kept_shard_entry(staging: str, shard: ShardSpec) -> ShardEntry:
    """The manifest entry of a shard kept from an interrupted run, read back from its file."""
    location = posixpath.join(staging, shard.name)
    file_digest, samples = shard_digests(location)
    planned = [sample.key for sample in shard.samples]
    if [key for key, _ in samples] != planned:
        raise DataFormatError(location, f"holds samples {[key for key, _ in samples][:3]}..., the "
                                        f"plan has {planned[:3]}...")
    return ShardEntry(shard.name, len(samples), file_digest, tuple(samples))


def write_manifest(staging: str, shards: list[ShardSpec], dataset: str, entries: dict[str, ShardEntry]) -> None:
    """The manifest of the shards in ``staging``: one row per sample, and each shard's count and SHA-256."""
    rows = [(shard.name, sample) for shard in shards for sample in shard.samples]
    columns = {
        "shard": [name for name, _ in rows],
        "key": [s.key for _, s in rows],
        "dataset": [dataset] * len(rows),
        "sequence": [s.sequence for _, s in rows],
        "group": [s.group for _, s in rows],
        "frame": [s.frame for _, s in rows],
        "split": [s.split for _, s in rows],
        "sha256": [digest for shard in shards for _, digest in entries[shard.name].sample_sha256],
    }
    manifest = manifest_bytes(columns, [entries[shard.name] for shard in shards])
    write_bytes(posixpath.join(staging, MANIFEST), manifest)

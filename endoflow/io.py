"""Atomic file output, the one implementation: a file or folder appears complete or not at all.

Every writer in endoflow goes through this module (``docs/architecture.md``, "Atomic writes"):

- :func:`atomic_path` yields a unique temporary name in the target's folder (so two processes writing the
  same target never share a temporary); on success the file is flushed to disk and renamed over the
  target, on failure the temporary is removed and the old target, if any, is left untouched; an ``OSError``
  of the write names the target (a full disk's error names no file).
- :func:`write_bytes`, :func:`write_text`, :func:`write_json`, :func:`write_csv`, :func:`save_figure` and
  :func:`save_torch` are built on it; :func:`load_plain_torch_file` reads torch files back, tensors and
  plain data only.
- :func:`staged_directory` fills a unique temporary sibling folder and swaps it in whole
  (:func:`replace_directory`), so a reader never sees a half-filled folder; what a killed run left staged
  for the same target is removed then (:func:`remove_abandoned`). A folder is only replaced when it
  is missing, empty or an earlier output of the same kind (:class:`OutputKind`), or when the user forces it;
  never when it is or holds a file the run reads (:func:`check_replaceable`, the one rule).
- :func:`atomic_location` is :func:`atomic_path` for any fsspec URL too: on an object store (``s3://``) the
  file is written locally and uploaded with a single put, so the object appears whole or not at all.

``durable=True`` (the default) fsyncs the file before the rename and the folder after it, so a power loss
cannot leave a renamed but empty file; bulk writers of many small files inside a staged folder (rendered
frames) pass ``durable=False``, as the folder swap is what makes them visible.
"""

from __future__ import annotations

import glob
import hashlib
import io
import json
import math
import os
import pickle
import posixpath
import shutil
import socket
import tempfile
import zipfile
from contextlib import contextmanager
from dataclasses import dataclass
from fnmatch import fnmatch
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Optional

import fsspec
from fsspec.implementations.local import LocalFileSystem

from endoflow.errors import DataFormatError

TEMPORARY_MARK = ".tmp-"
# this machine's name as temporaries carry it (process_mark): what a file name may hold, and no "@"
_HOST = "".join(c if c.isalnum() or c in ".-" else "_" for c in socket.gethostname())
_ZIP_MAGIC = b"PK\x03\x04"  # how every torch.save file begins


def temporary_sibling(path: Path, suffix: str = "") -> Path:
    """A new, unique, empty file beside ``path`` (``.<name>.tmp-XXXX``), created so no other process gets it.

    ``mkstemp`` makes it private (0600); it gets the mode a plain ``open`` would give, as the target will.
    """
    descriptor, name = tempfile.mkstemp(prefix=f".{path.name}{TEMPORARY_MARK}", suffix=suffix, dir=path.parent)
    os.fchmod(descriptor, 0o666 & ~_UMASK)
    os.close(descriptor)
    return Path(name)


def _read_umask() -> int:
    # os.umask can only be read by setting it: done once, at import, before any writer thread exists
    current = os.umask(0)
    os.umask(current)
    return current


_UMASK = _read_umask()


@contextmanager
def atomic_path(path: str | Path, durable: bool = True) -> Iterator[Path]:
    """Yield a temporary path to write ``path``'s content to; it replaces ``path`` only if the block succeeds.

    The temporary keeps ``path``'s suffix, for writers that choose a format by file name.
    """
    path = Path(path)
    with _naming_target(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = temporary_sibling(path, suffix=path.suffix)
    try:
        with _naming_target(path, temporary):
            yield temporary
            if durable:
                _fsync_file(temporary)
            os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    if durable:
        with _naming_target(path):
            _fsync_folder(path.parent)


@contextmanager
def _naming_target(target: str | Path, temporary: Path | None = None) -> Iterator[None]:
    """Re-raise an ``OSError`` of writing ``target`` naming ``target``: a full disk's error (``ENOSPC``) names no
    file, and one naming the temporary names a file that is gone. An error naming another file (an input the
    writer read) is raised as it is."""
    try:
        yield
    except OSError as error:
        if error.errno is None or not _about_written_file(error, Path(target), temporary):
            raise
        raise OSError(error.errno, f"{error.strerror} while writing", str(target)) from error


def _about_written_file(error: OSError, target: Path, temporary: Path | None) -> bool:
    """Whether ``error`` is about the file being written: it names no file, the target or its temporary."""
    if error.filename is None:
        return True
    name = Path(os.fsdecode(error.filename))
    return name in (target, temporary) or name.name.startswith(f".{target.name}{TEMPORARY_MARK}")


@contextmanager
def atomic_location(location: str | Path, durable: bool = True) -> Iterator[Path]:
    """:func:`atomic_path` for a local path or an fsspec URL: yields a local temporary to write the content to.

    On a local filesystem (a path, ``file://``) this is :func:`atomic_path`. Elsewhere there is no rename: the
    temporary is uploaded with one ``put`` when the block succeeds, and an object store shows an object only
    once its upload is complete; on failure nothing is uploaded.
    """
    if "://" not in str(location):  # a plain path, taken as it is (fsspec would read "::" in it as a chain)
        with atomic_path(location, durable) as temporary:
            yield temporary
        return
    fs, path = fsspec.core.url_to_fs(str(location))
    if isinstance(fs, LocalFileSystem):
        with atomic_path(path, durable) as temporary:
            yield temporary
        return
    with tempfile.TemporaryDirectory(prefix="endoflow-upload-") as folder:
        temporary = Path(folder) / posixpath.basename(path)
        with _naming_target(location, temporary):
            yield temporary
            fs.put_file(str(temporary), path)


def write_bytes(path: str | Path, data: bytes, durable: bool = True) -> None:
    """Write ``data`` to ``path`` (a local path or an fsspec URL) atomically (:func:`atomic_location`)."""
    with atomic_location(path, durable) as temporary:
        temporary.write_bytes(data)


def write_text(path: str | Path, text: str, durable: bool = True) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"), durable)


def write_json(path: str | Path, data: Any) -> None:
    """JSON with 2-space indentation and a final newline (numpy scalars and arrays become plain numbers).

    Raises:
        ValueError: naming ``path`` and the key, for a NaN or infinity (JSON has no such numbers: Python would
            write ``NaN``, which other JSON readers refuse); nothing is written then.
    """
    try:
        text = json.dumps(data, indent=2, default=_plain, allow_nan=False)
    except ValueError:
        key, value = _first_non_finite(json.loads(json.dumps(data, default=_plain)))
        raise ValueError(f"{path}: not written: {key} is {value}, a number JSON cannot hold") from None
    write_text(path, text + "\n")


def write_csv(path: str | Path, table: Any) -> None:
    """A pandas ``DataFrame`` as CSV without its index, floats to 6 significant digits."""
    with atomic_path(path) as temporary:
        table.to_csv(temporary, index=False, float_format="%.6g")


def save_figure(path: str | Path, figure: Any, dpi: int = 100) -> None:
    """Save a matplotlib figure as PNG at ``dpi`` and close it."""
    import matplotlib.pyplot as plt

    try:
        with atomic_path(path) as temporary:
            figure.savefig(temporary, format="png", dpi=dpi)
    finally:
        plt.close(figure)


def save_torch(path: str | Path, payload: Any) -> None:
    """``torch.save`` of tensors and plain data, atomically (load it back with ``weights_only=True``).

    Saved to memory first: torch names the zip's folder after the file it writes, which here would be the
    random temporary, so the same payload gives the same bytes only when saved to a buffer (folder ``archive``).
    """
    import torch

    buffer = io.BytesIO()
    torch.save(payload, buffer)
    write_bytes(path, buffer.getvalue())


def load_plain_torch_file(source: str | Path | bytes, what: str, name: Optional[str] = None) -> Any:
    """``torch.load(weights_only=True)`` of a path or of a file's bytes, with errors that name the file.

    The one loader of every torch file endoflow reads (what :func:`save_torch` writes). Anything that needs more
    than tensors and plain data to load (a pickled object, which could run code) is refused, as is a file that
    is not a torch archive at all (``torch.save`` writes zip archives).
    """
    import torch

    label = name or str(source)
    data = source if isinstance(source, bytes) else Path(source).read_bytes()
    if not data.startswith(_ZIP_MAGIC):
        raise DataFormatError(label, f"not a torch file (no zip archive header: truncated, empty or another kind of "
                                     f"file); expected {what}")
    try:
        return torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's text goes on to explain how to allowlist the global: advice we do not pass on
        reason = next((line.strip() for line in str(exc).splitlines() if "Unsupported" in line), "").split(". ")[0]
        raise DataFormatError(label, f"refused to load: it holds objects other than tensors and plain data, which "
                                     f"could run code ({reason or 'weights-only load failed'}); expected {what}") from None
    except (RuntimeError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:  # how torch reports damage
        raise DataFormatError(label, f"not a readable torch file, truncated or corrupt ({str(exc).splitlines()[0][:200]}); "
                                     f"expected {what}") from None


class OutputFolderError(RuntimeError):
    """A folder endoflow was asked to replace holds something it did not write, or what the run reads; the folder
    is left as it was."""


@dataclass(frozen=True)
class OutputKind:
    """What a folder endoflow replaces holds when endoflow wrote it: ``what`` names it in errors ("an endoflow
    reconstruction"); ``recognise(folder)`` says whether an existing, non-empty ``folder`` is one."""

    what: str
    recognise: Callable[[Path], bool]


def marked_output(what: str, file: str, **fields: Any) -> OutputKind:
    """Outputs recognised by ``file`` in them, a JSON object with ``fields``' values (a format marker)."""

    def recognise(folder: Path) -> bool:
        try:
            content = json.loads((folder / file).read_text())
        except (OSError, ValueError):  # missing, unreadable or not JSON (a decoding error is a ValueError)
            return False
        return isinstance(content, dict) and all(content.get(key) == value for key, value in fields.items())

    return OutputKind(what, recognise)


def files_only(what: str, patterns: tuple[str, ...]) -> OutputKind:
    """Outputs recognised by their files: every entry below the folder is a file whose name matches one of
    ``patterns`` (``fnmatch``); for folders without a record of their own, such as figures."""

    def recognise(folder: Path) -> bool:
        return all(entry.is_file() and not entry.is_symlink() and any(fnmatch(entry.name, p) for p in patterns)
                   for entry in _entries_below(folder))

    return OutputKind(what, recognise)


FIGURE_FOLDER = files_only("a folder of figures (PNG and CSV files only)", ("*.png", "*.csv"))


def check_replaceable(path: str | Path, kind: OutputKind, force: bool = False, inputs: Iterable[str | Path] = (),
                      force_option: Optional[str] = None) -> None:
    """The rule for every folder endoflow replaces: ``path`` may be replaced when it is missing, empty or
    ``kind``'s earlier output, or when ``force`` says so; never when it is or holds one of ``inputs`` (what the
    run reads), forced or not.

    Raises:
        OutputFolderError: naming ``path``, what it holds and how to proceed (``force_option``, where the
            caller has one, is how the user forces it).
    """
    path = Path(path)
    for item in inputs:
        if _is_within(Path(item), path):
            relation = "is" if _same_path(Path(item), path) else "holds"
            raise OutputFolderError(f"{path}: will not replace this folder: it {relation} {item}, which this run "
                                    f"reads; choose another output folder")
    if not path.exists():
        return
    if not path.is_dir():
        raise OutputFolderError(f"{path}: is a file, not a folder; choose a new or empty folder for the output")
    entries = sorted(path.iterdir())
    if not entries or force or kind.recognise(path):
        return
    forcing = (f", or pass {force_option} to replace it and everything in it" if force_option
               else ", or move what it holds elsewhere")
    raise OutputFolderError(f"{path}: will not replace a folder that is not {kind.what}: it holds "
                            f"{_listing(entries)}; choose a new or empty folder{forcing}")


@contextmanager
def staged_directory(path: str | Path, kind: OutputKind, force: bool = False, inputs: Iterable[str | Path] = (),
                     force_option: Optional[str] = None) -> Iterator[Path]:
    """Fill a unique temporary sibling folder, then swap it in for ``path`` only if the block succeeds.

    ``path`` is checked (:func:`check_replaceable`, with these arguments) before the block runs, so a refused
    folder costs no work, and again when it is replaced."""
    path = Path(path)
    inputs = tuple(inputs)
    check_replaceable(path, kind, force, inputs, force_option)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_abandoned(path.parent, f".{path.name}.partial-")
    staging = Path(tempfile.mkdtemp(prefix=owned_prefix(f".{path.name}.partial-"), dir=path.parent))
    staging.chmod(0o777 & ~_UMASK)  # mkdtemp's folder is private; the output is not
    try:
        yield staging
        replace_directory(staging, path, kind, force, inputs, force_option)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def replace_directory(staging: str | Path, path: str | Path, kind: OutputKind, force: bool = False,
                      inputs: Iterable[str | Path] = (), force_option: Optional[str] = None) -> None:
    """Put the complete folder ``staging`` in place of ``path`` (the old one is moved aside, then removed), if
    :func:`check_replaceable` allows it."""
    staging, path = Path(staging), Path(path)
    check_replaceable(path, kind, force, inputs, force_option)
    remove_abandoned(path.parent, f".{path.name}.old-")
    old = Path(tempfile.mkdtemp(prefix=owned_prefix(f".{path.name}.old-"), dir=path.parent))
    had_old = path.exists()
    if had_old:
        os.replace(path, old)  # renaming onto an empty folder replaces it
    try:
        os.replace(staging, path)
    except BaseException:
        if had_old:
            os.replace(old, path)  # put the previous output back: never leave neither
        raise
    finally:
        shutil.rmtree(old, ignore_errors=True)
    _fsync_folder(path.parent)


# ------------------------------------------------------------------------- what killed runs leave behind
def process_mark() -> str:
    """``<process id>@<machine>``: which process made a staging folder or opened a run, for
    :func:`ended_here` to tell later whether it is still running."""
    return f"{os.getpid()}@{_HOST}"


def ended_here(mark: str) -> bool:
    """Whether ``mark`` (a :func:`process_mark`) names a process of this machine that has ended; a process of
    another machine cannot be checked and counts as running."""
    pid, _, host = mark.partition("@")
    return host == _HOST and pid.isdigit() and not _running(int(pid))


def owned_prefix(prefix: str) -> str:
    """``prefix`` followed by this process's :func:`process_mark`: a temporary name whose owner
    :func:`remove_abandoned` can tell."""
    return f"{prefix}{process_mark()}-"


def remove_abandoned(folder: str | Path, prefix: str) -> list[Path]:
    """Remove the entries of ``folder`` named :func:`owned_prefix` ``(prefix)`` by a process that has ended on
    this machine: the staging folders and temporaries of runs that were killed or crashed before they could
    clean up. Those of running processes and of other machines stay. Returns what was removed."""
    removed = []
    for entry in Path(folder).glob(f"{glob.escape(prefix)}*@*"):
        mark = entry.name[len(prefix):].rsplit("-", 1)[0]  # mkdtemp's random tail has no "-"
        if ended_here(mark):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            removed.append(entry)
    return removed


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)  # signal 0: only asks whether the process exists
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, under another user
        return True
    return True


def _entries_below(folder: Path) -> Iterator[Path]:
    """Every file and link below ``folder`` (subfolders are looked into, links are not followed)."""
    for parent, folders, files in os.walk(folder):
        for name in (*folders, *files):
            entry = Path(parent) / name
            if not entry.is_dir() or entry.is_symlink():
                yield entry


def _listing(entries: list[Path], shown: int = 5) -> str:
    names = [entry.name + ("/" if entry.is_dir() else "") for entry in entries[:shown]]
    more = f" and {len(entries) - shown} more" if len(entries) > shown else ""
    return ", ".join(names) + more


def _is_within(inner: Path, outer: Path) -> bool:
    inner, outer = inner.resolve(), outer.resolve()
    return inner == outer or outer in inner.parents


def _same_path(a: Path, b: Path) -> bool:
    return a.resolve() == b.resolve()


def file_sha256(location: str | Path) -> str:
    """Hex SHA-256 of a file (a path or an fsspec URL), read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with fsspec.open(str(location), "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _fsync_file(path: Path) -> None:
    with open(path, "rb+") as handle:
        os.fsync(handle.fileno())


def _fsync_folder(folder: Path) -> None:
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:  # platforms where a folder cannot be opened: the rename is all we can do
        return
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _first_non_finite(data: Any, key: str = "") -> Optional[tuple[str, float]]:
    """The dotted key (list positions in brackets) and value of the first NaN or infinity in plain ``data``."""
    if isinstance(data, float) and not math.isfinite(data):
        return key or "the value", data
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else ()
    for name, value in items:
        found = _first_non_finite(value, f"{key}.{name}".lstrip(".") if isinstance(data, dict) else f"{key}[{name}]")
        if found:
            return found
    return None


def _plain(value: Any) -> Any:
    if hasattr(value, "item") and getattr(value, "ndim", 0) == 0:
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} to JSON")

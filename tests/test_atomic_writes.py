"""Atomic writes name the file they were writing when the disk says no, and leave no litter.

The round-3 audit's cases: a full disk (``ENOSPC``) during preprocessing or training ended in
``[Errno 28] No space left on device`` without a path. Every writer goes through :mod:`endoflow.io`, whose errors
now name the target; the temporary is removed and an earlier file is left as it was. And the hidden staging
folders of killed runs (``predictions/.<set>.partial-*``, ``.<out>.partial-*``) stayed forever: the next run that
stages the same target now removes them.
"""

from __future__ import annotations

import errno
import os
import subprocess
from pathlib import Path

import pytest

from endoflow import io
from endoflow.io import (
    FIGURE_FOLDER,
    TEMPORARY_MARK,
    atomic_path,
    ended_here,
    process_mark,
    save_torch,
    staged_directory,
    write_json,
)


def full_disk(*_args, **_kwargs) -> None:
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as the kernel reports it: no file named


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if TEMPORARY_MARK in p.name)


@pytest.mark.parametrize("write", [lambda p: write_json(p, {"a": 1}), lambda p: save_torch(p, {"a": 1})],
                         ids=["write_json", "save_torch"])
def test_a_full_disk_names_the_target_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path, monkeypatch,
                                                                                   write) -> None:
    target = tmp_path / "out" / "model.pt"
    target.parent.mkdir()
    target.write_bytes(b"earlier")
    monkeypatch.setattr(io, "_fsync_file", full_disk)  # where a full disk shows with delayed allocation

    with pytest.raises(OSError) as caught:
        write(target)

    assert caught.value.errno == errno.ENOSPC
    assert caught.value.filename == str(target)
    assert str(target) in str(caught.value)
    assert target.read_bytes() == b"earlier"
    assert leftovers(target.parent) == []


def test_an_error_naming_the_temporary_names_the_target_instead(tmp_path: Path) -> None:
    target = tmp_path / "history.csv"
    with pytest.raises(PermissionError) as caught:
        with atomic_path(target) as temporary:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(temporary))
    assert caught.value.filename == str(target)
    assert leftovers(tmp_path) == []


def test_an_error_about_another_file_is_raised_as_it_is(tmp_path: Path) -> None:
    source = tmp_path / "missing-input.png"
    with pytest.raises(FileNotFoundError) as caught:
        with atomic_path(tmp_path / "copy.png") as temporary:
            temporary.write_bytes(source.read_bytes())
    assert caught.value.filename == str(source)
    assert leftovers(tmp_path) == []


# ------------------------------------------------------------------------ what killed runs leave behind
def ended_process_mark() -> str:
    """The :func:`endoflow.io.process_mark` of a process of this machine that has ended."""
    process = subprocess.Popen(["true"])
    process.wait()
    return process_mark().replace(str(os.getpid()), str(process.pid), 1)


def test_staging_a_folder_removes_what_killed_runs_left_staged_for_it_and_nothing_else(tmp_path: Path) -> None:
    out = tmp_path / "simcol_3"
    killed = tmp_path / f".simcol_3.partial-{ended_process_mark()}-k1ll3d00"
    killed_swap = tmp_path / f".simcol_3.old-{ended_process_mark()}-k1ll3d01"
    running = tmp_path / f".simcol_3.partial-{process_mark()}-runn1ng0"
    elsewhere = tmp_path / f".simcol_3.partial-{ended_process_mark().split('@')[0]}@another-host-3lsewh3r"
    other_target = tmp_path / f".simcol_1.partial-{ended_process_mark()}-0th3r000"
    for folder in (killed, killed_swap, running, elsewhere, other_target):
        (folder / "partial").mkdir(parents=True)

    with staged_directory(out, FIGURE_FOLDER) as staging:
        (staging / "curves.png").write_bytes(b"\x89PNG")

    assert (out / "curves.png").exists()
    assert not killed.exists() and not killed_swap.exists()
    assert running.exists() and elsewhere.exists() and other_target.exists()
    assert sorted(p.name for p in tmp_path.iterdir() if ".partial-" in p.name or ".old-" in p.name) == sorted(
        p.name for p in (running, elsewhere, other_target))


def test_a_process_mark_tells_running_from_ended_processes_of_this_machine_only() -> None:
    assert not ended_here(process_mark())
    assert ended_here(ended_process_mark())
    assert not ended_here(ended_process_mark().split("@")[0] + "@another-host")
    assert not ended_here("") and not ended_here("run-id-without-a-mark")

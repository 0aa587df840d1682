"""Atomic writes name the file they were writing when the disk says no.

The round-3 audit's case: a full disk (``ENOSPC``) during preprocessing or training ended in
``[Errno 28] No space left on device`` without a path. Every writer goes through :mod:`endoflow.io`, whose errors
now name the target; the temporary is removed and an earlier file is left as it was.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from endoflow import io
from endoflow.io import TEMPORARY_MARK, atomic_path, save_torch, write_json


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

"""Errors that more than one layer raises: imported by the lowest layer (``endoflow/io.py``) and every one above.

A file that does not match its documented layout raises :class:`DataFormatError` wherever it is read: a dataset
by its reader, a shard by the loader, a torch file by :func:`endoflow.io.load_plain_torch_file`. Imports nothing
of endoflow.
"""

from __future__ import annotations

from pathlib import Path


class DataFormatError(ValueError):
    """Input does not match the documented layout. The message names the file and what was expected."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")

    def __reduce__(self):
        # Default exception pickling replays args (the joined message) into __init__, which takes two:
        # without this, an error raised in a worker process reaches the parent as a broken pool.
        return (type(self), (str(self.path), self.problem))

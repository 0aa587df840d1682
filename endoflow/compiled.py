"""Loops compiled by numba, for the per-pixel and per-voxel work that tensor code on a CPU does in many passes
over memory (the TSDF's integration, the tracker's costs and normal equations): how they are compiled and cached.
Imports nothing of endoflow, so every layer may use it."""

from __future__ import annotations

from typing import Callable

import numba


def compiled_loop(function: Callable) -> Callable:
    """``function`` compiled by numba without the GIL, cached on disk where numba finds a writable folder for it
    (a read-only install run by a user without a writable home has none: numba then refuses ``cache=True``).

    The loops run in the calling thread, one core: numba's own thread pool would contend with torch's on a small
    machine and, in its default layer, aborts the process when two threads call it at once. They release the GIL,
    so the threads that read frames ahead and write outputs behind go on meanwhile. Compiled on first use (a few
    seconds), then loaded from numba's cache beside the module or in the user's cache folder (``NUMBA_CACHE_DIR``
    sets another); where no cache folder is writable, compiled once per process instead."""
    try:
        return numba.njit(cache=True, nogil=True)(function)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return numba.njit(nogil=True)(function)


def compiled_part(function: Callable) -> Callable:
    """``function`` as a part of compiled loops, compiled into each loop that calls it (numba's ``inline="always"``,
    so it has no cache of its own: the loop's holds it). For a part with many arguments: called across the boundary
    of a function compiled on its own, the tracker's Jacobian rows of a point took its loop from 10.9 to 19.2 ms at
    480 px. Small parts (a bilinear sample, a projection) are better compiled on their own with ``compiled_loop``:
    inlined as well, they took the same loop to 18.9 ms."""
    return numba.njit(inline="always")(function)

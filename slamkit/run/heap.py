"""Returning freed C-heap memory to the operating system during long runs.

torch's CPU tensors and numpy arrays come from malloc. A mapping step allocates and frees many
tensors of a few megabytes whose sizes change with the map; glibc raises its mmap threshold after
such frees, so later ones come from the heap, and the freed holes stay resident while the live
tensors do not grow. `malloc_trim(0)` once per keyframe gives the free pages back; a fixed mmap
threshold would save more but slows mapping (docs/results.md, "The memory guard").
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim():
    """glibc's malloc_trim, or None where the C library has none (macOS, musl, Windows)."""
    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None
    if trim is not None:
        trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def release_free_memory() -> bool:
    """Return the C heap's free pages to the OS (glibc `malloc_trim(0)`); False where that is
    not available. Safe at any time from any thread: it only releases memory nobody uses."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True

"""Returning freed C-heap memory to the operating system during long runs.

torch's CPU tensors and numpy arrays come from malloc. A mapping step allocates and frees many
tensors of 0.1-10 MB whose sizes change with the map; glibc raises its mmap threshold after such
frees, so later ones come from the heap, and the freed holes stay resident. Measured on the
2000-frame synthetic sequence with the map capped at 200,000 Gaussians (docs/results.md, issue
9; benchmarks/heap.py): live tensors stay at ~38 MB while the heap's free bytes grow from 60 to
150 MB over 500-800 frames. `malloc_trim(0)` (~5 ms) gives free pages back: called once per
keyframe it left 47-66 MB less resident at frame 500, with run times within the shared machine's
noise (a fixed mmap threshold saved more but made mapping 40-100% slower).
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

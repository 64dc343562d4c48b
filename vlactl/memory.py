"""Keeping a long pass's heap from growing with the number of batches it has seen (glibc only; elsewhere a no-op).

glibc raises its mmap threshold each time a large block is freed, so later blocks of many sizes come from the heap,
whose freed pages it keeps: over a pass of `vlactl collect` the process grew by hundreds of MB before levelling off.
A fixed threshold (large blocks are mapped and unmapped again) and a trim after each batch group keep it flat
(README, measured). A threshold of 128 KB also kept it flat but slowed collection by 40%; at 4 MB only image
batches and the biggest activations are mapped.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

M_MMAP_THRESHOLD = -3  # mallopt's parameter number in glibc's malloc.h
MMAP_THRESHOLD = 4 << 20


@functools.cache
def _libc():
    name = ctypes.util.find_library("c")
    libc = ctypes.CDLL(name) if name else None
    return libc if hasattr(libc, "malloc_trim") and hasattr(libc, "mallopt") else None


def fix_mmap_threshold() -> None:
    """Blocks of MMAP_THRESHOLD and more are mapped from now on, and freed straight back to the system."""
    if _libc() is not None:
        _libc().mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)


def release_free_memory() -> None:
    """Hand the heap's free pages back to the system."""
    if _libc() is not None:
        _libc().malloc_trim(0)

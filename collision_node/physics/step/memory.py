"""The allocator's policy for a stepping process: keep freed memory for the next step.

A step allocates and frees arrays of every particle's size (the broadphase's
pair list when it is rebuilt, the solve's per-particle marks). glibc's
malloc serves blocks over a threshold from fresh ``mmap`` regions and
returns them to the system when they are freed, so the next step touches
new pages and pays a page fault for each; on this project's virtual machines
that cost 3 to 5 ms in the contact solve of a step after each rebuild of a
100,000-particle gas. Raising the ``mmap`` threshold and the trim threshold
(``ALLOCATOR_MMAP_THRESHOLD``, ``ALLOCATOR_TRIM_THRESHOLD``) keeps freed
blocks in the process for reuse, as jemalloc or tcmalloc do. The resident
memory then stays near the process's peak instead of shrinking between
steps. Elsewhere than glibc (or with ``KEEP_FREED_MEMORY`` False) nothing
changes. Results never depend on it.
"""

from __future__ import annotations

import ctypes
import ctypes.util

from ..model.tunables import (ALLOCATOR_MMAP_THRESHOLD, ALLOCATOR_TRIM_THRESHOLD,
                              KEEP_FREED_MEMORY)

# mallopt's parameter numbers (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

_applied = False


def keep_freed_memory() -> bool:
    """Set the allocator's thresholds once per process; return whether glibc took them."""
    global _applied
    if _applied or not KEEP_FREED_MEMORY:
        return _applied
    _applied = True
    try:
        libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6')
        mallopt = libc.mallopt
    except (OSError, AttributeError):       # not glibc: its own policy stays
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt takes a C int: a larger value would wrap (a trim threshold of 0
    # returns memory at every free, the opposite of the intent).
    largest = 2 ** 31 - 1
    return bool(mallopt(_M_MMAP_THRESHOLD, min(int(ALLOCATOR_MMAP_THRESHOLD), largest))
                and mallopt(_M_TRIM_THRESHOLD, min(int(ALLOCATOR_TRIM_THRESHOLD), largest)))

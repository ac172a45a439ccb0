"""glibc malloc settings for a process that segments one large frame after another.

A 640x480 frame allocates tens of megabytes of short-lived arrays (the cloud's copies, the voxel
table, the output message). By default glibc gives such memory back to the kernel as it is
freed: blocks above its mmap threshold at once, the top of the heap once more than the trim
threshold is free, and a worker thread's whole heap as soon as it empties. The next frame then
faults the same pages in again, zeroed by the kernel: on the bench's 20-part bin, run on a
worker thread as the node runs it, ~8,000 minor faults and ~30 ms of kernel time per frame.
:func:`retain_freed_memory` keeps that memory in the process for the next frame (the peak
resident size is the same: it is the memory one frame needs).
"""
from __future__ import annotations

import ctypes
import sys

# mallopt parameters, from glibc's <malloc.h>
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8

KEEP_FREE_BYTES = 128 << 20   # free memory kept at the top of the heap
HEAP_BLOCK_LIMIT = 32 << 20   # blocks up to this size come from the heap (glibc's maximum)

retained = False  # whether this process runs with the settings (the bench reports it)


def retain_freed_memory(keep_free: int = KEEP_FREE_BYTES,
                        heap_block_limit: int = HEAP_BLOCK_LIMIT) -> bool:
    """Keep freed memory for reuse instead of returning it to the kernel; True when applied.

    Call first thing in ``main``, before any thread starts: one arena for all threads (the
    node segments on a worker thread, whose own arena would be unmapped whenever it empties)
    only covers threads that have not allocated yet. A no-op (False) where the C library has
    no ``mallopt`` (musl, macOS).
    """
    global retained
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    ok = all(mallopt(param, value) == 1 for param, value in (
        (M_ARENA_MAX, 1), (M_MMAP_THRESHOLD, heap_block_limit), (M_TRIM_THRESHOLD, keep_free)))
    retained = retained or ok
    return ok

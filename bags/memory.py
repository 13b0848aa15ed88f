"""Memory reuse for the processes that replay bags: :func:`keep_freed_memory`.

A replay allocates and frees arrays of a few megabytes per frame (decoded GT layers, the
prediction, masks, the scorer's temporaries). glibc serves allocations above its mmap threshold
(dynamic, from 128 kB) with fresh pages from the kernel and unmaps them on free, so every frame
faults in its memory again: about 700 minor page faults a frame, which cost more than the
reading itself on this project's virtual machines. Raising the threshold (and the amount of
freed memory kept before it is returned) makes those arrays reuse the heap instead.

The setting is process-wide, so only the processes that replay call it: ``bev-bag replay`` and
``bev-bag evaluate``'s workers, and the scoring process (:mod:`bags.replay.score_process`). An
environment that sets ``MALLOC_MMAP_THRESHOLD_`` or ``MALLOC_TRIM_THRESHOLD_`` itself wins.
"""

from __future__ import annotations

import ctypes
import os
import sys

#: glibc's ``mallopt`` parameters
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: allocations up to this size come from the heap (its freed blocks are reused)
MMAP_THRESHOLD = 64 << 20
#: freed memory at the top of the heap kept for reuse, up to this much
TRIM_THRESHOLD = 256 << 20


def keep_freed_memory() -> bool:
    """Serve allocations up to :data:`MMAP_THRESHOLD` from the heap and keep up to
    :data:`TRIM_THRESHOLD` of freed memory (glibc's ``mallopt``); ``False`` where that is not
    glibc or the environment already chose (module docstring).
    """
    if not sys.platform.startswith("linux") or {"MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"} & set(os.environ):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))


__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory"]

"""Host memory: keep what torch frees inside the process, so large CPU tensors reuse pages already mapped.

glibc serves every allocation of 32 MiB or more (and smaller ones above its dynamic threshold) with a fresh ``mmap``
and unmaps it on ``free``, so each new tensor of that size page-faults all its pages in, zero-filled, again. A paper-
size frame builds and frees per-chunk tensors of hundreds of megabytes many times: the kernel's share of its CPU time
was 41% (one preview and one full frame of the viewer at ``scale=paper``, 1 thread: 74 s system of 179 s, 31 million
minor page faults; the late per-view products of a chunk were the slow ones because they allocate the most). With
``keep_freed_memory`` allocations come from the heap (``M_MMAP_MAX`` 0) and freed memory stays in the process up to
the heap is never trimmed (``M_TRIM_THRESHOLD`` -1): the same frames took 5 s of system time and 1.6 million faults.
The price is resident memory that stays at its peak (and some fragmentation: 6.5 GB against 5.3 GB at that size).
"""

from __future__ import annotations

import ctypes
import platform

M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
"""``mallopt`` parameters (glibc's ``malloc.h``)."""

NEVER_TRIM = -1
"""``M_TRIM_THRESHOLD`` value that turns trimming off (``man mallopt``): freed memory is never returned to the kernel."""


def keep_freed_memory() -> bool:
    """Tune glibc's malloc for this process as the module docstring says; True when applied, False where the C
    library is not glibc (macOS, musl), whose allocators this does not concern. Irreversible for the process and
    harmless to call again."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(None)
    return bool(libc.mallopt(M_MMAP_MAX, 0)) and bool(libc.mallopt(M_TRIM_THRESHOLD, NEVER_TRIM))

"""Keep freed memory for the next frame: glibc's heap thresholds fixed at their ceiling.

Every frame allocates and frees the same image-sized buffers (OpenCV's derivative and
eigenvalue images, numpy temporaries, the decoded image message: 0.3 to 11 MiB each).
glibc serves a request above its mmap threshold with a fresh mapping and gives freed memory
at the top of the heap back to the kernel once more than its trim threshold is free. Its
dynamic rule raises the mmap threshold to the largest mapped block freed so far and the trim
threshold to twice that, but a frame frees several such blocks together, more than the trim
threshold, so the heap's top goes back to the kernel and is faulted in again the next frame:
measured on the engine at 640x480 with 1000 features, about 1700 page faults a frame (each
a kernel entry and a zeroed page), 4 to 6 ms of system time a frame.

:func:`keep_freed_memory` fixes the two thresholds where glibc's own rule would take them
after the largest block it raises them for (mmap threshold 32 MiB, its ceiling on 64-bit
systems; trim threshold twice that, the pair its rule keeps), so freed blocks are reused
from the heap: no page faults after the first frames, the same results bit for bit. Memory
is still bounded: a freed block is reused, not leaked; the process keeps up to the trim
threshold of free heap instead of returning it.

Called first by the product's entry points (``owl_node``, ``owl_process``) and by the tools
that time the engine. A process whose environment already sets glibc's malloc variables
(``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_`` or ``glibc.malloc`` tunables) keeps
them: that is how to run without this (e.g. ``MALLOC_TRIM_THRESHOLD_=131072``, glibc's
default). Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys
from collections.abc import Mapping

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory"]

#: Blocks up to this size come from the heap, bytes (glibc's DEFAULT_MMAP_THRESHOLD_MAX on
#: 64-bit systems: its dynamic threshold never goes higher).
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free heap kept before returning memory to the kernel, bytes (twice the mmap threshold,
#: as glibc's dynamic rule sets it).
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD
# mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Environment variables through which glibc takes these settings itself.
_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")


def keep_freed_memory(environ: Mapping[str, str] | None = None) -> str:
    """Fix glibc's mmap and trim thresholds (module docstring) unless the environment sets
    them; returns one line saying what was done, for a log."""
    env = os.environ if environ is None else environ
    given = [k for k in _ENV if k in env]
    if "glibc.malloc." in env.get("GLIBC_TUNABLES", ""):
        given.append("GLIBC_TUNABLES")
    if given:
        return f"heap thresholds left as the environment sets them ({', '.join(given)})"
    if not sys.platform.startswith("linux"):
        return f"heap thresholds unchanged: not glibc ({sys.platform})"
    libc = ctypes.CDLL(None)  # the C library this process already runs on
    if not hasattr(libc, "gnu_get_libc_version"):
        return "heap thresholds unchanged: the C library is not glibc"
    mallopt = libc.mallopt
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # both: setting either one switches off glibc's adjustment of the other
    done = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD), mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    if done != (1, 1):
        return f"heap thresholds: glibc's mallopt returned {done} (1 = set)"
    return (
        f"heap: blocks up to {MMAP_THRESHOLD >> 20} MiB reused, "
        f"up to {TRIM_THRESHOLD >> 20} MiB of free heap kept"
    )

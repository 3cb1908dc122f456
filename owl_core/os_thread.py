"""The operating system's name of the calling thread, so that ``top -H``, ``htop``,
``ps -T`` and ``/proc/PID/task/TID/comm`` show which of the product's threads takes the CPU.

Python (before 3.14) names its threads for itself only; the kernel keeps the process's
name for every thread ("python"). On Linux, :func:`name_os_thread` sets the calling
thread's kernel name (``prctl(PR_SET_NAME)``, at most 15 bytes); elsewhere it does nothing.
"""

from __future__ import annotations

import ctypes
import sys
import threading

__all__ = ["NAME_BYTES", "name_os_thread"]

_PR_SET_NAME = 15  # linux/prctl.h
#: The kernel's limit for a thread name, bytes (16 with the terminating NUL).
NAME_BYTES = 15


def name_os_thread(name: str | None = None) -> bool:
    """Give the calling thread ``name`` (default: its Python name), cut to
    :data:`NAME_BYTES` bytes, as its kernel name; returns whether it was set."""
    if not sys.platform.startswith("linux"):
        return False
    text = threading.current_thread().name if name is None else name
    raw = text.encode("utf-8", "replace")[:NAME_BYTES]
    try:
        libc = ctypes.CDLL(None)  # the C library this process already runs on
        return int(libc.prctl(_PR_SET_NAME, ctypes.c_char_p(raw), 0, 0, 0)) == 0
    except (OSError, AttributeError):  # no prctl in this C library
        return False

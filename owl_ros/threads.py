"""Compute threads: numpy's BLAS on one thread in the product's processes, and one OpenCV and
BLAS thread for the tools that time the engine.

OpenBLAS (numpy's BLAS from PyPI) runs a call above its size thresholds on a pool of
threads, and between calls those threads busy-wait for the next one for about a tenth of a
second. The dense stage makes such calls every frame (float64 dot products over a 320x240
plane, a product with a transposed operand), so in the node with dense outputs on one BLAS
thread spun almost without pause: measured with ``owl_latency --case vga30 -p dense:=true``
(dense at 10 Hz), the thread took about 70 % of a core, the node's CPU was 170 % instead of
133 %, and the sparse engine, starved of it, kept fewer frames. A 76 800-element float64 dot
every 33 ms, alone in a process, keeps a whole core busy (1.0 s of CPU a second against 0.04
s on one thread). The product's arrays gain nothing from a second BLAS thread, so the
entry points (``owl_node``, ``owl_process``) call :func:`one_blas_thread` first. OpenCV
keeps its own pool: its second thread is worth more than it costs there (docs/performance.md).

``OMP_NUM_THREADS`` and friends are read by OpenBLAS when numpy is first imported, so setting
them in ``main()`` comes too late; threadpoolctl changes the limit of the already-loaded
BLAS instead. Importing this module changes nothing (threadpoolctl is imported only when
called, since importing it sets ``KMP_DUPLICATE_LIB_OK``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import cv2

__all__ = ["BLAS_ENV", "one_blas_thread", "one_thread"]

#: Environment variables through which a user sets the BLAS thread count; when one is set,
#: :func:`one_blas_thread` leaves the count to it.
BLAS_ENV = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread(environ: Mapping[str, str] | None = None) -> str:
    """Limit every loaded BLAS library of this process to one thread unless the environment
    sets a thread count (module docstring); returns one line saying what was done, for a log."""
    env = os.environ if environ is None else environ
    given = [k for k in BLAS_ENV if k in env]
    if given:
        return f"BLAS threads left as the environment sets them ({', '.join(given)})"
    from threadpoolctl import threadpool_limits  # here: importing it sets KMP_DUPLICATE_LIB_OK

    threadpool_limits(limits=1, user_api="blas")
    return "BLAS: one thread (its idle threads would busy-wait between calls)"


def one_thread() -> None:
    """Limit OpenCV and every loaded BLAS/OpenMP library of this process to one thread, for
    measurements: the timing tools report per-thread figures."""
    from threadpoolctl import threadpool_limits  # here: importing it sets KMP_DUPLICATE_LIB_OK

    cv2.setNumThreads(1)
    threadpool_limits(limits=1)

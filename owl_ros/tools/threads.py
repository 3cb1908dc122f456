"""One compute thread for measurements: OpenCV's pool and numpy's BLAS, set at run time.

The timing tools report per-thread figures. ``OMP_NUM_THREADS`` and friends are read by
OpenBLAS when numpy is first imported, so setting them in ``main()`` comes too late;
threadpoolctl changes the limit of the already-loaded BLAS instead. Call it from a tool's
``main()``: importing this module changes nothing (threadpoolctl itself is imported only
when called, since importing it sets ``KMP_DUPLICATE_LIB_OK``).
"""

from __future__ import annotations

import cv2


def one_thread() -> None:
    """Limit OpenCV and every loaded BLAS/OpenMP library of this process to one thread."""
    from threadpoolctl import threadpool_limits  # here: importing it sets KMP_DUPLICATE_LIB_OK

    cv2.setNumThreads(1)
    threadpool_limits(limits=1)

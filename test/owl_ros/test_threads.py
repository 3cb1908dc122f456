"""owl_ros.threads: numpy's BLAS on one thread in the product's processes, so that no idle
BLAS thread busy-waits beside the engine."""

from __future__ import annotations

import os
import textwrap
from typing import TYPE_CHECKING

from owl_ros import threads

if TYPE_CHECKING:
    from conftest import SnippetRunner

# The dense stage's pattern: a float64 dot over a 320x240 plane, then 33 ms of other work
# (here a sleep), thirty times. Prints the BLAS thread counts threadpoolctl sees, the
# process's CPU seconds over the loop and one_blas_thread's line.
_FRAMES = textwrap.dedent(
    """
    import json, sys, time
    import numpy as np
    from threadpoolctl import threadpool_info
    from owl_ros import threads
    line = threads.one_blas_thread() if sys.argv[1] == "one" else "untouched"
    a = np.random.default_rng(0).random(320 * 240)
    cpu = time.process_time()
    for _ in range(30):
        float(a @ a)
        time.sleep(0.033)
    cpu = time.process_time() - cpu
    blas = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    print(json.dumps({"blas_threads": blas, "cpu_s": cpu, "line": line}))
    """
)


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in threads.BLAS_ENV}


def test_blas_runs_on_one_thread_and_does_not_spin(run_snippet: SnippetRunner) -> None:
    one = run_snippet(_FRAMES, "one", _clean_env())
    assert one["blas_threads"] and set(one["blas_threads"]) == {1}, one
    assert "one thread" in str(one["line"])
    # 30 dots of 0.1 ms and 1 s of sleeping: a spinning BLAS thread would add up to a
    # second of CPU (measured: 1.0 s with OpenBLAS's default threads on two cores)
    assert one["cpu_s"] < 0.3, one


def test_the_environment_s_own_thread_count_wins(run_snippet: SnippetRunner) -> None:
    kept = run_snippet(_FRAMES, "one", _clean_env() | {"OPENBLAS_NUM_THREADS": "2"})
    assert "OPENBLAS_NUM_THREADS" in str(kept["line"])
    assert kept["blas_threads"] and set(kept["blas_threads"]) == {2}, kept
    line = threads.one_blas_thread({"OMP_NUM_THREADS": "4"})
    assert "OMP_NUM_THREADS" in line

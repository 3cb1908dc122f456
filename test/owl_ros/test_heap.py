"""owl_ros.heap: freed image-sized blocks are reused instead of faulted in again."""

from __future__ import annotations

import os
import sys
import textwrap
from typing import TYPE_CHECKING

import pytest

from owl_ros import heap

if TYPE_CHECKING:
    from conftest import SnippetRunner

# A frame's pattern: several image-sized blocks allocated, written, then freed together
# (more free heap at once than glibc's dynamic trim threshold), forty times. Prints the
# minor page faults per frame after the first frames and keep_freed_memory's line.
_FRAMES = textwrap.dedent(
    """
    import json, resource, sys
    import numpy as np
    from owl_ros import heap
    line = heap.keep_freed_memory() if sys.argv[1] == "keep" else "untouched"
    def frame():
        blocks = [np.ones(300_000, dtype=np.float32) for _ in range(6)]  # 1.2 MB each
        return float(sum(b[::4096].sum() for b in blocks))
    for _ in range(5):
        frame()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(40):
        frame()
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 40
    print(json.dumps({"faults_per_frame": faults, "line": line}))
    """
)


def _clean_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env.pop("GLIBC_TUNABLES", None)
    return env


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc heap")
def test_frames_stop_faulting_their_blocks_in_again(run_snippet: SnippetRunner) -> None:
    # 6 blocks x 1.2 MB = 1760 pages a frame: glibc's own rule gives most of them back to
    # the kernel after every frame; with the thresholds fixed they stay in the heap.
    env = _clean_env()
    plain = run_snippet(_FRAMES, "plain", env)
    kept = run_snippet(_FRAMES, "keep", env)
    assert float(plain["faults_per_frame"]) > 1000.0, plain  # the problem is there
    assert float(kept["faults_per_frame"]) < 20.0, kept
    assert "32 MiB" in str(kept["line"]) and "64 MiB" in str(kept["line"])


def test_the_environment_s_own_settings_win(run_snippet: SnippetRunner) -> None:
    env = _clean_env() | {"MALLOC_TRIM_THRESHOLD_": "131072"}
    kept = run_snippet(_FRAMES, "keep", env)
    assert "MALLOC_TRIM_THRESHOLD_" in str(kept["line"])
    assert float(kept["faults_per_frame"]) > 1000.0, kept  # glibc's behaviour, untouched
    line = heap.keep_freed_memory({"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=131072"})
    assert "GLIBC_TUNABLES" in line

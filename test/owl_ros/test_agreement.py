"""OWL's heading against the 5-point heading on the same tracks of the real handheld walk."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from bags.cli.importers.cli import main as import_main
from owl_ros.tools.agreement import heading_agreement

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "realsense_walk"


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="the whole walk at gap 4: OWL vs 5-point median 39.2 deg against 31.1 deg between "
    "the two two-view estimates (39.3 before the tracks' deformation correction, 40.9 "
    "against 29.8 before 5f5c3c3; 64.6 before the bias filter measured its frames' "
    "scatter). Every pair of estimators "
    "disagrees by 24 to 40 deg median here; read as a three-cornered hat OWL, the 5-point "
    "and the gyro-aided two-view have errors of about 30, 26 and 15 deg on these tracks",
)
def test_owl_heading_agrees_with_the_5_point_heading_on_the_walk(tmp_path: Path) -> None:
    """The bound: the two-view estimates' own scatter on the same frames.

    There is no ground truth; the 5-point heading's error on these tracks is not known
    either, but the gyro-aided two-view heading (independent of the engine: the raw gyro,
    translation only) measures it: their median disagreement is the spread a second
    estimator of the same heading shows here. OWL agreeing with the 5-point heading no worse
    than that is the bound; at gap 4 (0.24 s at 17 Hz, the gap with most 5-point headings),
    over the whole 10 s recording.
    """
    if not (SHARED / "mav0").is_dir():
        msg = f"shared recording realsense_walk not found ({SHARED})"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    bag = tmp_path / "walk"
    assert import_main([str(SHARED), str(bag), "-q"]) == 0  # the whole recording
    out = heading_agreement(bag, (4,))
    r = out["per_gap"][4]
    assert r["both"] >= 100  # enough frames to judge
    assert r["median_deg"] <= r["gyro_vs_5pt_median_deg"], r

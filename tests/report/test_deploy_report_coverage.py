"""The Deployment section says when a pooled comparison leaves the end of each run out
(only whole blocks of deploy.compare_interval_s are compared)."""

from __future__ import annotations

import pandas as pd

from macromicro_sumo.deploy.compare import REFERENCE_SIMULATED, SUMMARY_COLUMNS
from macromicro_sumo.report.deploy import deployment_markdown, pooled_coverage


def summary(compare_s: float, pooled_n: int, detector_n: int) -> pd.DataFrame:
    """A summary of 11 stations x 4 runs of 720 s at 30 s loops (Bremen's shape)."""
    row = dict.fromkeys(SUMMARY_COLUMNS, 0.0) | {
        "method": "policy",
        "reference": REFERENCE_SIMULATED,
        "runs": 4,
        "compare_interval_s": compare_s,
        "detector_interval_s": 30.0,
        "station_intervals": pooled_n,
        "station_intervals_detector_interval": detector_n,
    }
    return pd.DataFrame([row], columns=SUMMARY_COLUMNS)


def test_blocks_that_leave_the_end_out_are_named_with_their_share() -> None:
    # 300 s blocks of 720 s runs: 2 per run and station, 600 of 720 s compared.
    s = summary(300.0, 11 * 4 * 2, 11 * 4 * 24)
    assert abs(pooled_coverage(s) - 600 / 720) < 1e-12
    text = deployment_markdown(s)
    assert "Only whole blocks of 300 s are compared: they hold 83% of the detectors'" in text


def test_blocks_that_tile_the_run_say_nothing_more() -> None:
    for compare_s, blocks in ((240.0, 3), (360.0, 2)):
        s = summary(compare_s, 11 * 4 * blocks, 11 * 4 * 24)
        assert pooled_coverage(s) == 1.0
        assert "Only whole blocks" not in deployment_markdown(s)
    # At the detectors' own interval nothing is pooled, and an old summary has no counts.
    assert "Only whole blocks" not in deployment_markdown(summary(30.0, 1056, 1056))
    old = summary(300.0, 88, 1056).drop(columns=["station_intervals_detector_interval"])
    assert pooled_coverage(old) != pooled_coverage(old)  # NaN
    assert "Only whole blocks" not in deployment_markdown(old)

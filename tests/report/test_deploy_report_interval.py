"""The Deployment section at a pooled comparison interval (deploy.compare_interval_s): the
targets judged at it, the detectors' own shares beside them."""

from __future__ import annotations

import pandas as pd

from macromicro_sumo.deploy.compare import REFERENCE_SIMULATED, SUMMARY_COLUMNS
from macromicro_sumo.report.deploy import deployment_markdown


def summary(compare_s: float, detector_s: float) -> pd.DataFrame:
    row = dict.fromkeys(SUMMARY_COLUMNS, 0.0) | {
        "method": "policy",
        "reference": REFERENCE_SIMULATED,
        "runs": 4,
        "compare_interval_s": compare_s,
        "detector_interval_s": detector_s,
        "share_geh_below_5": 0.95,
        "share_speed_within_5pct": 0.84,
        "share_geh_below_5_detector_interval": 0.77,
        "share_speed_within_5pct_detector_interval": 0.71,
    }
    return pd.DataFrame([row], columns=SUMMARY_COLUMNS)


def test_a_pooled_summary_states_both_intervals() -> None:
    text = deployment_markdown(summary(300.0, 30.0))
    assert "Station-intervals are of 300 s (`deploy.compare_interval_s`)" in text
    assert "the targets are judged at 300 s" in text
    assert "| GEH < 5 at 30 s (%) | speed within 5% at 30 s (%) |" in text
    assert "| 95.0 | 84.0 | 77.0 | 71.0 |" in text
    assert (
        "flow GEH < 5 in 95.0% of station-intervals of 300 s (target at least 85%): met; "
        "at the detectors' 30 s: 77.0%." in text
    )
    assert "in 84.0% of station-intervals of 300 s (target at least 85%): missed; " in text


def test_the_detectors_own_interval_is_named_and_not_repeated() -> None:
    text = deployment_markdown(summary(30.0, 30.0))
    assert "Station-intervals are the detectors' own 30 s (`deploy.compare_interval_s = 0`)" in text
    assert "at 30 s (%)" not in text and "at the detectors'" not in text
    # A summary written before the key: no interval named, the table as it was.
    old = summary(30.0, 30.0).drop(columns=["compare_interval_s", "detector_interval_s"])
    assert "Station-intervals are" not in deployment_markdown(old)

"""deploy.intervals: detectors' intervals pooled into the comparison interval, checked by
hand on a small detectors.csv (the comparison of real folders: tests/deploy/test_compare.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from macromicro_sumo.deploy.compare import ALL_LANES, station_table
from macromicro_sumo.deploy.intervals import block_factor, interval_length_s, pool_detectors
from macromicro_sumo.errors import UserError

# Two loops across the lanes of one station and a lane-area detector, four 30 s intervals
# and the partial one SUMO writes when a run ends (120 s to 120.5 s).
COUNTS = {"a": [10, 5, 0, 8], "b": [4, 6, 2, 0]}  # vehicles per interval
SPEEDS = {"a": [20.0, 25.0, np.nan, 30.0], "b": [30.0, 15.0, 10.0, np.nan]}  # harmonic means
E2_SPEED = [12.0, 18.0, 9.0, 6.0]
E2_SECONDS = [60.0, 20.0, 0.0, 30.0]  # vehicle-seconds on the detector


def detectors() -> pd.DataFrame:
    rows = []
    bounds = [(30.0 * i, 30.0 * (i + 1)) for i in range(4)] + [(120.0, 120.5)]
    for i, (b, e) in enumerate(bounds):
        j = min(i, 3)
        for det, lane, arc in (("a", 0, 500.0), ("b", 1, 502.0)):
            n, v = COUNTS[det][j], SPEEDS[det][j]
            rows.append(
                {
                    "run": 0, "detector_id": det, "kind": "e1", "lane_index": lane,
                    "arc_m": arc, "begin_s": b, "end_s": e, "n_veh": n,
                    "flow_vph": n * 3600.0 / (e - b), "speed_mps": v,
                    "density_vpkm": n * 3600.0 / (e - b) / v / 3.6 if n else 0.0,
                    "sampled_seconds_s": np.nan,
                }
            )  # fmt: skip
        rows.append(
            {
                "run": 0, "detector_id": "c", "kind": "e2", "lane_index": 0, "arc_m": 900.0,
                "begin_s": b, "end_s": e, "n_veh": 3, "flow_vph": np.nan,
                "speed_mps": E2_SPEED[j] if E2_SECONDS[j] else np.nan,
                "density_vpkm": 2.0 * (j + 1), "sampled_seconds_s": E2_SECONDS[j],
            }
        )  # fmt: skip
    return pd.DataFrame(rows)


def test_pairs_of_intervals_pool_counts_harmonic_and_timed_speeds() -> None:
    det = detectors()
    pooled = pool_detectors(det, 2)
    assert list(pooled.columns) == list(det.columns)
    # Two whole blocks of 60 s per detector; the partial interval is left out.
    assert len(pooled) == 6 and set(pooled["end_s"] - pooled["begin_s"]) == {60.0}
    a0 = pooled[(pooled["detector_id"] == "a") & (pooled["begin_s"] == 0.0)].iloc[0]
    # 10 + 5 vehicles in 60 s is 900 veh/h; their space-mean speed 15 / (10/20 + 5/25).
    assert (a0["n_veh"], a0["flow_vph"]) == (15, pytest.approx(900.0))
    assert a0["speed_mps"] == pytest.approx(15 / (10 / 20 + 5 / 25))
    # Density averaged over the intervals is the pooled flow / pooled speed / 3.6.
    assert a0["density_vpkm"] == pytest.approx(a0["flow_vph"] / a0["speed_mps"] / 3.6)
    # Nobody passed in 60-90 s: the block's speed is the 8 vehicles of 90-120 s.
    a1 = pooled[(pooled["detector_id"] == "a") & (pooled["begin_s"] == 60.0)].iloc[0]
    assert (a1["flow_vph"], a1["speed_mps"]) == (pytest.approx(480.0), pytest.approx(30.0))
    # The lane-area detector: speeds weighted by time on it, no flow, density averaged.
    c = pooled[pooled["detector_id"] == "c"].sort_values("begin_s")
    assert c["speed_mps"].iloc[0] == pytest.approx((60 * 12 + 20 * 18) / 80)
    assert c["speed_mps"].iloc[1] == pytest.approx(6.0)  # 0 s at 9 m/s count nothing
    assert c["flow_vph"].isna().all()
    np.testing.assert_allclose(c["density_vpkm"], [3.0, 7.0])
    np.testing.assert_allclose(c["sampled_seconds_s"], [80.0, 30.0])


def test_the_pooled_station_is_the_station_of_every_vehicle_in_the_block() -> None:
    st = station_table(pool_detectors(detectors(), 4))
    row = st[(st["station"] == "e1_501m") & (st["lane"] == ALL_LANES)].iloc[0]
    n = sum(COUNTS["a"]) + sum(COUNTS["b"])
    inv = sum(k / v for d in "ab" for k, v in zip(COUNTS[d], SPEEDS[d], strict=True) if k and v > 0)
    assert (row["begin_s"], row["end_s"]) == (0.0, 120.0)
    assert row["flow_vph"] == pytest.approx(n * 3600 / 120)
    assert row["speed_mps"] == pytest.approx(n / inv)


def test_blocks_of_one_are_the_detectors_own_intervals() -> None:
    det = detectors()
    a, b = station_table(det), station_table(pool_detectors(det, 1))
    pd.testing.assert_frame_equal(a, b, check_dtype=False)


def test_three_intervals_of_four_leave_an_incomplete_block_out() -> None:
    pooled = pool_detectors(detectors(), 3)
    assert set(pooled["begin_s"]) == {0.0} and set(pooled["end_s"]) == {90.0}


def test_the_comparison_interval_must_be_a_multiple_of_the_detectors() -> None:
    assert interval_length_s(detectors()) == 30.0
    assert block_factor(0.0, 30.0, "x") == 1 and block_factor(300.0, 30.0, "x") == 10
    for bad in (45.0, 15.0):
        with pytest.raises(UserError) as err:
            block_factor(bad, 30.0, "gt/detectors.csv")
        msg = str(err.value)
        assert "\n" not in msg
        assert msg.startswith(f"gt/detectors.csv: deploy.compare_interval_s = {bad:g} ")
        assert "accepted: 0 (the detectors' own) or k x 30 s" in msg

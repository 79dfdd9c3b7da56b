"""Stations of the comparison: loops across the lanes of one position form a station, two
loops on one lane never do (measured on SUMO's game/cross, stop 32: the tool's own loops at
25.7 m and 30.0 m of its one-lane approach were one station, its flow twice the road's)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from macromicro_sumo.deploy.stations import ALL_LANES, STATION_TOLERANCE_M, station_table


def loops(lane: list[int], arc_m: list[float], flow_vph: list[float]) -> pd.DataFrame:
    """One 90 s interval of E1 loops, every vehicle at 14 m/s."""
    n = np.asarray(flow_vph) * 90.0 / 3600.0
    return pd.DataFrame(
        {
            "run": 0,
            "detector_id": [f"d{i}" for i in range(len(lane))],
            "kind": "e1",
            "lane_index": lane,
            "arc_m": arc_m,
            "begin_s": 0.0,
            "end_s": 90.0,
            "n_veh": n,
            "flow_vph": flow_vph,
            "speed_mps": 14.0,
            "density_vpkm": np.asarray(flow_vph) / 14.0 / 3.6,
        }
    )


def test_two_loops_on_one_lane_are_two_stations() -> None:
    # game/cross's approach: a spacing loop and a boundary loop 4.3 m apart on lane 0.
    assert STATION_TOLERANCE_M > 30.0 - 25.7
    st = station_table(loops([0, 0], [25.7, 30.0], [520.0, 520.0]))
    road = st[st["lane"] == ALL_LANES]
    assert len(road) == 2
    # Each is the road's flow, not the two loops' sum.
    np.testing.assert_allclose(road["flow_vph"], [520.0, 520.0])
    np.testing.assert_allclose(road["arc_m"], [25.7, 30.0])
    assert road["station"].nunique() == 2


def test_the_lanes_of_one_position_stay_one_station_beside_a_second_loop() -> None:
    # Three lanes at 65 m (a user's loops 1 m apart across the carriageway) and, 3 m on,
    # a second loop on lane 1: the three lanes one station, the fourth loop its own.
    st = station_table(loops([0, 1, 2, 1], [65.0, 66.0, 65.5, 69.0], [120.0, 320.0, 80.0, 300.0]))
    road = st[st["lane"] == ALL_LANES].sort_values("arc_m")
    assert road["flow_vph"].tolist() == pytest.approx([520.0, 300.0])
    three = road["station"].iloc[0]
    assert sorted(st.loc[st["station"] == three, "lane"]) == [ALL_LANES, 0, 1, 2]
    # No station has two rows for one lane and interval (the comparison matches on them).
    assert not st.duplicated(["run", "station", "lane", "begin_s", "end_s"]).any()


def test_stations_with_the_same_rounded_position_get_distinct_names() -> None:
    st = station_table(loops([0, 0], [330.2, 330.4], [400.0, 400.0]))
    road = st[st["lane"] == ALL_LANES]
    assert road["station"].nunique() == 2
    np.testing.assert_allclose(road["flow_vph"], [400.0, 400.0])

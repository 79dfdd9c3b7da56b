"""truth.section_rows.SectionRows (record_run's rows): the steps' reads kept and filtered
to the section together, then one sort, give the frame of a filter per step and pandas'
stable sort by time, lane and arc (record_run before hR37's change), bit for bit."""

from __future__ import annotations

from itertools import repeat
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import sumo

from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.sumo.states import VehicleStates
from macromicro_sumo.truth import section_rows
from macromicro_sumo.truth.section_rows import SectionRows

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross"


def per_step(section, steps: list[tuple[float, VehicleStates]]) -> pd.DataFrame:
    """record_run's rows as before: each step filtered, then pandas' stable sort."""
    lane_code = {lane: i for i, lane in enumerate(section.lanes)}
    lane_rows = np.array(list(section.lanes.values()), dtype=float).reshape(-1, 4)
    rows = []
    for t, st in steps:
        code = np.fromiter(map(lane_code.get, st.lanes, repeat(-1)), np.int64, len(st.ids))
        for i in (code >= 0).nonzero()[0]:
            edge, lane, start, scale = lane_rows[code[i]]
            arc = start + st.pos_m[i] * scale
            rows.append(
                (t, st.ids[i], int(lane), int(edge), arc, st.speed_mps[i], st.accel_mps2[i])
            )
    columns = ["time_s", "vehicle_id", "lane_index", "edge_index", "arc_m", "speed_mps"]
    df = pd.DataFrame(rows, columns=[*columns, "accel_mps2"])
    by = ["time_s", "lane_index", "arc_m"]
    return df.sort_values(by, kind="stable").reset_index(drop=True)


def collected(section, steps, flush_every: int) -> pd.DataFrame:
    rows = SectionRows(section)
    for i, (t, st) in enumerate(steps):
        if i % flush_every == flush_every - 1:
            rows.flush()
        rows.add(t, st)
    cols, vids = rows.columns()
    return pd.DataFrame({"time_s": cols.pop("time_s"), "vehicle_id": vids, **cols})


def cross_steps(n: int) -> list[tuple[float, VehicleStates]]:
    opts = SumoOptions(CROSS / "cross.net.xml", (), 1.0, 3, route_files=(CROSS / "cross.rou.xml",))
    sim = Simulation(opts)
    steps = []
    try:
        for _ in range(n):
            sim.step()
            steps.append((sim.time_s(), sim.vehicle_states()))
    finally:
        sim.close()
    return steps


def test_rows_of_a_real_run_equal_a_filter_per_step() -> None:
    section = read_section(CROSS / "cross.net.xml", ["1fi", "1si", "2o", "2fo"], False)
    steps = cross_steps(300)
    want = per_step(section, steps)
    # Vehicles off the section (the other approaches) and steps with nobody on it.
    assert 0 < len(want) < sum(len(st.ids) for _, st in steps)
    for every in (1, 7, 500):
        got = collected(section, steps, every)
        pd.testing.assert_frame_equal(got, want, check_exact=True)


def test_ties_keep_sumo_order_and_an_empty_run_has_the_empty_columns() -> None:
    section = read_section(CROSS / "cross.net.xml", ["1fi", "1si"], False)
    lane = next(iter(section.lanes))
    st = VehicleStates(
        ("a", "b", "c", "d"),
        [lane, "elsewhere", lane, lane],
        np.array([5.0, 1.0, 5.0, 2.0]),
        np.array([1.0, 2.0, 3.0, 4.0]),
        np.zeros(4),
    )
    steps = [(1.0, st), (2.0, VehicleStates((), [], *(np.empty(0),) * 3)), (3.0, st)]
    got = collected(section, steps, 2)
    pd.testing.assert_frame_equal(got, per_step(section, steps), check_exact=True)
    assert got["vehicle_id"].tolist() == ["d", "a", "c"] * 2  # a before c: SUMO's order
    cols, vids = SectionRows(section).columns()
    assert vids == [] and all(v == [] for v in cols.values())


def test_the_steps_kept_are_filtered_once_they_hold_pending_rows(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A large network around a short section: the reads kept stay bounded by vehicles,
    not only by the memory check's steps; the frame stays the same."""
    section = read_section(CROSS / "cross.net.xml", ["1fi", "1si", "2o", "2fo"], False)
    steps = cross_steps(300)
    monkeypatch.setattr(section_rows, "PENDING_ROWS", 40)
    rows = SectionRows(section)
    most = 0
    for t, st in steps:
        rows.add(t, st)
        most = max(most, sum(len(s.ids) for s in rows.pending))
    assert most < 40 and max(len(st.ids) for _, st in steps) < 40
    cols, vids = rows.columns()
    got = pd.DataFrame({"time_s": cols.pop("time_s"), "vehicle_id": vids, **cols})
    pd.testing.assert_frame_equal(got, per_step(section, steps), check_exact=True)

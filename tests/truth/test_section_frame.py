"""truth.section_rows.SectionRows.frame (the end of record_run): the run's frame built a
vehicle at a time (IDs as codes, each vehicle's vType and observed flag taken by code, the
rows sorted by the arcs' ranks) is the frame record_run built a row at a time, bit for bit,
with the same dtypes and the same counts of vehicles."""

from __future__ import annotations

from itertools import repeat
from pathlib import Path

import numpy as np
import pandas as pd
import sumo

from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.sumo.states import VehicleStates
from macromicro_sumo.truth.section_rows import SectionRows

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross"


def by_row(rows: SectionRows, run: int, types: dict, observed: dict) -> tuple:
    """record_run's end before: a row at a time, lexsort's order, pandas' nunique."""
    cols = {k: np.concatenate(v) for k, v in rows.chunks.items()}
    where = rows.lane_rows[cols.pop("lane_code")]
    step = np.repeat(np.arange(len(rows.counts)), rows.counts)
    arc = where[:, 2] + cols["pos_m"] * where[:, 3]
    order = np.lexsort((arc, where[:, 1], step))
    vids = np.array(rows.vids, dtype=object)[order].tolist()
    df = pd.DataFrame(
        {
            "time_s": np.repeat(np.array(rows.times, dtype=float), rows.counts)[order],
            "vehicle_id": vids,
            "lane_index": where[order, 1].astype(np.int64),
            "edge_index": where[order, 0].astype(np.int64),
            "arc_m": arc[order],
            "speed_mps": cols["speed_mps"][order],
            "accel_mps2": cols["accel_mps2"][order],
        }
    )
    df.insert(0, "run", run)
    df.insert(3, "vtype", [types.get(v, np.nan) for v in vids])
    df.insert(4, "observed", np.fromiter(map(observed.get, vids, repeat(True)), bool, len(vids)))
    seen = int(df["vehicle_id"].nunique())
    return df, seen, int(df.loc[df["observed"], "vehicle_id"].nunique())


def same(got: tuple, want: tuple) -> None:
    pd.testing.assert_frame_equal(got[0], want[0], check_exact=True)
    assert got[0].dtypes.equals(want[0].dtypes) and got[1:] == want[1:]


def cross_rows() -> tuple[SectionRows, dict[str, str], dict[str, bool]]:
    section = read_section(CROSS / "cross.net.xml", ["1fi", "1si", "2o", "2fo"], False)
    opts = SumoOptions(CROSS / "cross.net.xml", (), 1.0, 3, route_files=(CROSS / "cross.rou.xml",))
    sim = Simulation(opts)
    rows, types = SectionRows(section), {}
    try:
        for _ in range(300):
            sim.step()
            for vid in sim.departed():
                types[vid] = sim.vehicle_type(vid)
            rows.add(sim.time_s(), sim.vehicle_states())
    finally:
        sim.close()
    observed = {v: i % 3 == 0 for i, v in enumerate(types)}
    return rows, types, observed


def test_the_frame_of_a_real_run_is_the_frame_built_a_row_at_a_time() -> None:
    rows, types, observed = cross_rows()
    rows.flush()
    want = by_row(rows, 4, types, observed)
    assert len(want[0]) > 100 and 0 < want[2] < want[1]  # observed and hidden vehicles
    assert want[0]["vtype"].nunique() > 1
    same(rows.frame(4, types, observed), want)
    # A vehicle without a vType: NaN there (what Series.map gave), the rest as ever.
    gone = want[0]["vehicle_id"].iloc[0]
    fewer = {v: t for v, t in types.items() if v != gone}
    got = rows.frame(4, fewer, observed)
    same(got, by_row(rows, 4, fewer, observed))
    assert got[0]["vtype"].isna().sum() == (want[0]["vehicle_id"] == gone).sum() > 0


def test_tied_and_repeated_arcs_keep_sumo_order() -> None:
    """Equal arcs on one lane and step keep SUMO's order; the ranks of many equal arcs
    across steps and lanes sort as lexsort does."""
    section = read_section(CROSS / "cross.net.xml", ["1fi", "1si"], False)
    lanes = list(section.lanes)
    rng = np.random.default_rng(7)
    rows = SectionRows(section)
    for t in range(1, 40):
        n = int(rng.integers(0, 12))
        ids = tuple(f"v{int(i)}" for i in rng.integers(0, 15, n))
        pos = rng.integers(0, 4, n).astype(float) * 2.5  # few values: many ties
        lane = [lanes[int(i)] for i in rng.integers(0, len(lanes), n)]
        rows.add(float(t), VehicleStates(ids, lane, pos, rng.normal(size=n), rng.normal(size=n)))
    rows.flush()
    types = {f"v{i}": f"t{i % 4}" for i in range(15)}
    observed = {f"v{i}": i % 2 == 0 for i in range(15)}
    same(rows.frame(0, types, observed), by_row(rows, 0, types, observed))


def test_an_empty_run_has_the_empty_frame() -> None:
    section = read_section(CROSS / "cross.net.xml", ["1fi", "1si"], False)
    df, seen, seen_observed = SectionRows(section).frame(2, {}, {})
    assert df.empty and seen == seen_observed == 0
    cols = ["run", "time_s", "vehicle_id", "vtype", "observed", "lane_index", "edge_index"]
    assert list(df.columns) == [*cols, "arc_m", "speed_mps", "accel_mps2"]

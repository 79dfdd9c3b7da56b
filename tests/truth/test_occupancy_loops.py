"""Dual loops (``detectors.auto_occupancy_loop_m``): a point E1 for the counts and speeds, a
second E1 with a length beside it for the occupancy only; real SUMO runs."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
from test_hidden_count import merge_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import DetectorSpec
from macromicro_sumo.truth.density import profile_integral
from macromicro_sumo.truth.section_detectors import Placed, detectors_xml
from macromicro_sumo.truth.section_macro import LINE_CUT_M, cut_at_lines, loop_densities


def with_loops(toml: Path, loop_m: float) -> Path:
    text = toml.read_text().replace(
        "[detectors]\n", f"[detectors]\nauto_occupancy_loop_m = {loop_m}\n"
    )
    out = toml.with_name(f"dual_{loop_m:g}.toml")
    out.write_text(text)
    return out


def test_only_the_tools_own_loops_get_an_occupancy_loop() -> None:
    own = DetectorSpec("auto_a_0_50", "e1", "a_0", 50.0, 2.0, 30.0, "")
    user = DetectorSpec("mine", "e1", "a_0", 80.0, 2.0, 30.0, "")
    near = DetectorSpec("auto_a_0_1", "e1", "a_0", 1.0, 2.0, 30.0, "")
    xml = detectors_xml(
        [Placed(own, "auto", 0, 50.0), Placed(user, "user", 0, 80.0), Placed(near, "auto", 0, 1)],
        30.0,
    )
    loops = re.findall(r'<inductionLoop id="([^"]+)"[^>]*pos="([\d.]+)"( length="([\d.]+)")?', xml)
    got = {i: (float(p), ln) for i, p, _, ln in loops}
    # Ends at the point loop (50 - 2), from the lane's start where that is nearer.
    assert got == {
        "auto_a_0_50": (50.0, ""),
        "o_auto_a_0_50": (48.0, "2"),
        "mine": (80.0, ""),
        "auto_a_0_1": (1.0, ""),
        "o_auto_a_0_1": (0.0, "2"),
    }


def test_dual_loops_read_the_queue_and_keep_the_counts(tmp_path: Path) -> None:
    """The same run with point loops and with 2 m occupancy loops: the counts, flows and
    speeds are the same (the loops do not change the simulation), the occupancy is the
    2 m loop's (higher where vehicles stand), and the density divides by vehicle + loop."""
    toml = merge_scenario(tmp_path, 1300.0, 400.0, 6.0, boundary=True)
    point = load_scenario(toml)
    assert "auto_occupancy_loop_m" not in point.to_dict()["detectors"]  # digests stay
    dets = {}
    for m in (0.0, 2.0):
        gt = tmp_path / f"gt_{m:g}"
        assert main(["simulate", str(with_loops(toml, m)), "--out", str(gt), "--quiet"]) == 0
        dets[m] = pd.read_csv(gt / "detectors.csv")
    a, b = dets[0.0], dets[2.0]
    keys = ["run", "detector_id", "begin_s"]
    b = b.set_index(keys).loc[a.set_index(keys).index].reset_index()
    for col in ("n_veh", "flow_vph", "speed_mps"):
        np.testing.assert_array_equal(a[col].to_numpy(), b[col].to_numpy())
    e1 = (b["kind"] == "e1").to_numpy()
    assert (a.loc[e1, "length_m"] == 0).all() and (b.loc[e1, "length_m"] == 2.0).all()
    slow = e1 & (a["speed_mps"] <= 7.0).to_numpy()
    assert slow.sum() > 20  # the queue from the lane drop crawls over loops
    # Each vehicle covers a 2 m loop over 2 m more of its travel (measured +12 points).
    assert b.loc[slow, "occupancy_pct"].mean() > a.loc[slow, "occupancy_pct"].mean() + 5.0
    free = e1 & (a["speed_mps"] >= 20.0).to_numpy()
    ratio = b.loc[free, "occupancy_pct"].sum() / a.loc[free, "occupancy_pct"].sum()
    assert 1.2 < ratio < 1.6  # (5-12 m + 2 m) / (5-12 m) in free flow
    passages = pd.read_csv(tmp_path / "gt_2" / "detector_passages.csv", dtype={"vehicle_id": str})
    k = loop_densities(b.iloc[np.flatnonzero(slow)], passages)
    k0 = loop_densities(b.iloc[np.flatnonzero(slow)].assign(length_m=0.0), passages)
    assert (k < k0).all()  # occupancy / (vehicle + 2 m), not / vehicle


def test_the_density_steps_at_a_stop_line() -> None:
    """A stop bar reading a queue (120 veh/km) 0.5 m before the line, the next station with
    a value 30 m past it (20): past the line the stretch reads the next station's density,
    not a line from the queue's (a station with no value is skipped)."""
    per_station = pd.Series([40.0, 120.0, np.nan, 20.0], index=[0.0, 99.5, 110.0, 130.0])
    cut = cut_at_lines(per_station, [100.0])
    assert cut.index.is_monotonic_increasing and len(cut) == 5

    def vehicles(k: pd.Series, lo: float, hi: float) -> float:  # an open 200 m section
        return profile_integral(k.index.to_numpy(), k.to_numpy(), 200.0, False, lo, hi)

    lo, hi = 100.0 + LINE_CUT_M, 130.0
    assert np.isclose(vehicles(cut, lo, hi), 20.0 * (hi - lo) / 1000.0)
    assert vehicles(per_station, lo, hi) > 1.5 * vehicles(cut, lo, hi)
    # Up to the stop bar nothing moves.
    assert np.isclose(vehicles(cut, 0.0, 99.5), vehicles(per_station, 0.0, 99.5))
    assert cut_at_lines(per_station, [140.0]) is per_station  # no station past that line

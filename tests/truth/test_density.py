"""Density from loops and the hidden-count estimate: hand-computed values, and a queue over
the loops of a tiny network in real SUMO."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import dump_toml, netconvert

from macromicro_sumo.cli import main
from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.density import (
    anchored_counts,
    cumulative_count,
    cumulative_mean,
    flow_speed_density,
    free_flow_weight,
    local_line,
    occupancy_density,
    occupancy_weight,
    point_density,
    profile_integral,
    projected_passages,
)
from macromicro_sumo.truth.hidden_count import k_estimates
from macromicro_sumo.truth.section_macro import detector_macro, k_summary
from macromicro_sumo.truth.stations import StationRecord


def test_occupancy_and_flow_speed_densities() -> None:
    # 10% of the time occupied by 5 m cars: one car per 50 m, 20 veh/km.
    assert occupancy_density(np.array([10.0]), np.array([5.0]))[0] == pytest.approx(20.0)
    # A 2 m loop under the same cars: 10% / 7 m.
    assert occupancy_density(np.array([10.0]), np.array([5.0]), 2.0)[0] == pytest.approx(
        100.0 / 7.0
    )
    # 1800 veh/h = 0.5 veh/s at 25 m/s: 0.02 veh/m.
    k = flow_speed_density(np.array([1800.0, 0.0]), np.array([25.0, np.nan]))
    assert k[0] == pytest.approx(20.0)
    assert np.isnan(k[1])


def test_occupancy_and_flow_speed_agree_on_steady_passages() -> None:
    # 60 s, three 5 m cars at 10 m/s over a point loop: each covers it 0.5 s, so 1.5 s of
    # 60 s = 2.5% occupancy and 2.5% / 5 m = 5 veh/km; 180 veh/h / 36 km/h = 5 veh/km too.
    occ = 100.0 * 3 * (5.0 / 10.0) / 60.0
    assert occ == pytest.approx(2.5)
    assert occupancy_density(np.array([occ]), np.array([5.0]))[0] == pytest.approx(5.0)
    assert flow_speed_density(np.array([180.0]), np.array([10.0]))[0] == pytest.approx(5.0)


def test_blend_by_speed_regime() -> None:
    w = occupancy_weight(np.array([2.0, 5.0, 7.5, 10.0, 30.0, np.nan]))
    np.testing.assert_allclose(w, [1.0, 1.0, 0.5, 0.0, 0.0, 1.0])
    # At 7.5 m/s: half of occupancy's 40 veh/km and half of flow / speed's
    # 1800 / 3.6 / 7.5 = 66.67 veh/km.
    k = point_density(np.array([1800.0]), np.array([7.5]), np.array([20.0]), np.array([5.0]))
    assert k[0] == pytest.approx(0.5 * 40.0 + 0.5 * 1800.0 / 3.6 / 7.5)
    # A queue standing over the loop: nobody passes (no speed), the loop is 90% occupied.
    k = point_density(np.array([0.0]), np.array([np.nan]), np.array([90.0]), np.array([6.0]))
    assert k[0] == pytest.approx(150.0)


def test_interpolation_between_stations() -> None:
    # Stations at 100 m (10 veh/km) and 300 m (30 veh/km) on a 400 m open section:
    # 100 m at 10, 200 m rising 10 -> 30 (mean 20), 100 m at 30: 1 + 4 + 3 vehicles.
    arcs, k = np.array([300.0, 100.0]), np.array([30.0, 10.0])
    assert profile_integral(arcs, k, 400.0, False) == pytest.approx(8.0)
    assert profile_integral(arcs, k, 400.0, False, 100.0, 200.0) == pytest.approx(1.5)
    # Closed: 300 -> 500 (= 100) falls 30 -> 10; [300, 400] mean 25, [0, 100] mean 15.
    assert profile_integral(arcs, k, 400.0, True) == pytest.approx(2.5 + 1.5 + 4.0)
    # A silent station (NaN) drops out: the other one holds the section.
    assert profile_integral(arcs, np.array([np.nan, 10.0]), 400.0, False) == pytest.approx(4.0)


def test_input_output_counts() -> None:
    t = np.array([1.0, 3.0])
    np.testing.assert_allclose(cumulative_count(t, np.array([0.0, 1.0, 2.0, 5.0])), [0, 0, 1, 2])
    # Over [0, 4): 0 until 1, 1 until 3, 2 until 4: (0 * 1 + 1 * 2 + 2 * 1) / 4.
    assert cumulative_mean(t, 0.0, 4.0) == pytest.approx(1.0)
    assert local_line(np.array([0.0, 1.0, 2.0]), np.array([1.0, 3.0, 5.0]), 4.0) == pytest.approx(
        9.0
    )
    # Input-output counts off by 7 everywhere, the density estimate right on average:
    # anchored, they are right.
    centres = np.array([30.0, 90.0, 150.0])
    io_means = np.array([1.0, 2.0, 3.0])
    dens = io_means + 7.0 + np.array([0.5, -1.0, 0.5])  # no trend: the line is flat at 7
    out = anchored_counts(
        np.array([2.0, 4.0]), io_means, dens, centres, np.array([90.0, 95.0]), 600
    )
    np.testing.assert_allclose(out, [9.0, 11.0])


def test_weighted_anchor_and_free_flow_weight() -> None:
    np.testing.assert_allclose(free_flow_weight(np.array([2.0, 7.5, 12.0])), [0.02, 0.5, 1.0])
    # The third interval is congested (weight 0): its biased density estimate is left out
    # and the one constant of the whole record is 7.
    centres = np.array([30.0, 90.0, 150.0])
    io_means = np.array([1.0, 2.0, 3.0])
    dens = io_means + np.array([7.0, 7.0, 10.0])
    out = anchored_counts(
        np.array([2.0, 4.0]),
        io_means,
        dens,
        centres,
        np.array([90.0, 500.0]),
        np.inf,
        np.array([1.0, 1.0, 0.0]),
    )
    np.testing.assert_allclose(out, [9.0, 11.0])
    # Weighted line: the zero-weight point does not bend it (y = x through the first two).
    x, y = np.array([0.0, 1.0, 2.0, 3.0]), np.array([0.0, 1.0, 2.0, 9.0])
    assert local_line(x, y, 5.0, np.array([1.0, 1.0, 1.0, 0.0])) == pytest.approx(5.0)


def test_end_pieces_projected_from_passages() -> None:
    # Passages at 10, 12 and 20 s at 10, 5 and 20 m/s; 50 m of road beyond the station
    # takes them 5, 10 and 2.5 s.
    p, v = np.array([10.0, 12.0, 20.0]), np.array([10.0, 5.0, 20.0])
    # Upstream at 9 s: the first two pass within their 5 and 10 s, the third (11 s) not.
    np.testing.assert_allclose(projected_passages(p, v, np.array([9.0]), 50.0, True), [2.0])
    # Downstream at 21 s: passed 11, 9 and 1 s ago; only the last two are within reach.
    # At 15 s: the first passed exactly 5 s ago (at the far end, gone), the second 3 s ago.
    np.testing.assert_allclose(
        projected_passages(p, v, np.array([21.0, 15.0]), 50.0, False), [2.0, 1.0]
    )
    # A standing vehicle counts at the crawl speed: 50 m at 0.5 m/s is 100 s of reach.
    assert projected_passages(np.array([0.0]), np.array([0.0]), np.array([60.0]), 50.0, False)[
        0
    ] == pytest.approx(1.0)


def queue_network(folder: Path) -> Path:
    """A one-lane 575 m road; a vehicle stops 60 s at 560 m, a queue grows behind it over
    the loops, then drains."""
    net = netconvert(
        folder,
        '<node id="a" x="0" y="0"/><node id="b" x="575" y="0"/><node id="c" x="675" y="0"/>',
        '<edge id="r" from="a" to="b" numLanes="1" speed="20"/>'
        '<edge id="x" from="b" to="c" numLanes="1" speed="20"/>',
        name="q",
    )
    (folder / "q.rou.xml").write_text(
        '<routes><vType id="car" length="5" minGap="2.5"/>'
        '<route id="rt" edges="r x"/>'
        '<flow id="f" type="car" route="rt" begin="0" end="400" vehsPerHour="1400" '
        'departSpeed="max"/>'
        '<vehicle id="blocker" type="car" route="rt" depart="20">'
        '<stop lane="r_0" endPos="560" duration="60"/></vehicle></routes>'
    )
    table = {
        "name": "queue",
        "seed": 3,
        "network": {
            "kind": "sumo",
            "net_file": str(net),
            "route_files": [str(folder / "q.rou.xml")],
        },
        "section": {"edges": ["r"], "closed": False},
        "instrumented": {"penetration": 0.2},
        "simulation": {"warmup_s": 30.0, "duration_s": 120.0, "n_runs": 1},
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 100.0, "k_window_s": 30.0},
        "generator": {"snapshot_every_s": 5.0},
    }
    path = folder / "queue.toml"
    path.write_text(dump_toml(table))
    return path


def test_queue_over_loops_is_counted(tmp_path: Path) -> None:
    gt = tmp_path / "gt"
    assert main(["simulate", str(queue_network(tmp_path)), "--out", str(gt), "--quiet"]) == 0
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str})
    assert (traj["speed_mps"] < 1.0).mean() > 0.3  # the queue is there
    section = Section.read(gt / "section.json")
    det = pd.read_csv(gt / "detectors.csv")
    pas = pd.read_csv(gt / "detector_passages.csv", dtype={"vehicle_id": str})
    # Loops with a queue standing over them for a whole interval pass nobody.
    assert ((det["n_veh"] == 0) & (det["occupancy_pct"] > 90.0)).any()
    scenario = json.loads((gt / "manifest.json").read_text())["scenario"]
    macro = detector_macro(det, pas, scenario["simulation"]["warmup_s"], 7.5, section)
    k = k_estimates(traj, macro, section, 5.0, 30.0, StationRecord(det, pas))
    err = k_summary(k, section)["mean_abs_error_per_lane_veh"]
    err_fs = float(np.abs(k["k_est_flow_speed"] - k["k_true"]).mean())
    # The queue grows and drains within the 30 s intervals of a 120 s run (few intervals
    # to anchor on): about 2 vehicles off, where flow / speed misses by about 10.
    assert err <= 2.5
    assert err < 0.5 * err_fs

"""A signal approach's density estimate with dual loops (``detectors.auto_occupancy_loop_m``):
each loop's occupancy density at any speed (``section_macro.edie_densities``) and a profile
that rises toward the stop line as ``density.rising_integral`` (stop 44)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from test_signal_counts import queued_scenario, simulated

from macromicro_sumo.data.section import at_snapshot_times
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.inputs import read_net
from macromicro_sumo.truth.density import RISE_POWER, profile_integral, rising_integral
from macromicro_sumo.truth.interval_counts import interval_record
from macromicro_sumo.truth.section_macro import edie_densities
from macromicro_sumo.truth.signal_counts import (
    approaches,
    arrivals,
    cumulative,
    density_constant,
)
from macromicro_sumo.truth.signal_lines import stop_lines


def test_the_density_rises_toward_the_line_as_the_power() -> None:
    """Hand values: 100 m from 40 to 160 veh/km rising, then 50 m from 160 to 100 falling
    (linear), then 50 m flat at 100."""
    arcs, k = np.array([0.0, 100.0, 150.0, 200.0]), np.array([40.0, 160.0, 100.0, 100.0])
    assert RISE_POWER == 2.0
    rising = 0.1 * (40.0 + 120.0 / 3.0)  # the lower density plus the rise over 3
    falling, flat = 0.05 * 130.0, 0.05 * 100.0
    assert np.isclose(rising_integral(arcs, k, 0.0, 200.0), rising + falling + flat)
    # Where it does not rise, the trapezoid rule (``profile_integral``'s), here from 120 m.
    assert np.isclose(
        rising_integral(arcs, k, 120.0, 200.0), profile_integral(arcs, k, 200.0, False, 120.0)
    )
    assert rising_integral(arcs, k, 0.0, 100.0) < profile_integral(
        arcs, k, 200.0, False, 0.0, 100.0
    )
    assert np.isnan(rising_integral(arcs, np.full(4, np.nan), 0.0, 200.0))


def test_a_dual_loops_density_is_its_occupancys_at_any_speed() -> None:
    """Two loops flowing freely at 25 veh/km (effective lengths 7 and 5 m: the run's 6 m),
    then a third interval in which loop ``a`` (2 m long) reads 40% occupancy at 9 m/s: its
    density is 0.4 / 6 m, not the speed blend's; the point loop ``b`` keeps its own."""
    det = pd.DataFrame(
        {
            "run": 0,
            "detector_id": ["a", "b", "a", "b", "a", "b"],
            "kind": "e1",
            "flow_vph": [1800.0, 1800.0, 1800.0, 1800.0, 900.0, 900.0],
            "speed_mps": [20.0, 20.0, 20.0, 20.0, 9.0, 9.0],
            "occupancy_pct": [17.5, 12.5, 17.5, 12.5, 40.0, 40.0],
            "length_m": [2.0, 0.0, 2.0, 0.0, 2.0, 0.0],
            "k_point_vpkm": [25.0, 25.0, 25.0, 25.0, 30.0, 30.0],
        }
    )
    k = edie_densities(det)["k_point_vpkm"].to_numpy()
    np.testing.assert_allclose(k[[0, 2, 4]], [175.0 / 6.0, 175.0 / 6.0, 400.0 / 6.0])
    np.testing.assert_array_equal(k[[1, 3, 5]], [25.0, 25.0, 30.0])


def test_dual_loops_put_a_queued_approach_on_its_count(tmp_path: Path) -> None:
    """The queue that never clears (``queued_scenario``) with 2 m occupancy loops, from
    240 s on: the approach's density constant (its count less the counted in and out) is
    the true one within a vehicle (12.74 against 13.0 measured), and at least a vehicle
    nearer than with the speed-regime blend of flow / speed and occupancy on a linear
    profile, what point loops keep (11.32)."""
    toml = queued_scenario(tmp_path)
    toml.write_text(
        toml.read_text().replace("[detectors]\n", "[detectors]\nauto_occupancy_loop_m = 2.0\n")
    )
    gt, net_file = simulated(tmp_path, lambda _: toml, "q.net.xml")
    section = Section.read(gt / "section.json")
    det = pd.read_csv(gt / "detectors.csv")
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    det, traj = det[det["begin_s"] >= 240.0], traj[traj["time_s"] >= 240.0]
    assert (det.loc[det["kind"] == "e1", "length_m"] == 2.0).all()
    record = interval_record(det, section, read_net(net_file), net_file)
    assert record is not None
    lines = stop_lines(net_file, section)
    (a,) = approaches(record.det, section, lines, record.side_arcs)

    def io(x: np.ndarray) -> np.ndarray:
        return arrivals(record.det, a, x) - cumulative(record.det, a.bar_m, x, a.line)

    snaps = at_snapshot_times(traj, 10.0)
    times = np.sort(snaps["time_s"].unique())
    by_t = snaps.groupby("time_s")["arc_m"]
    true = np.array(
        [((x >= a.up_m) & (x < a.bar_m)).sum() for x in (by_t.get_group(t) for t in times)]
    )
    c_true = float(np.median(true - io(times)))
    dual = density_constant(record.det, section, a, io)
    point = density_constant(record.det.assign(length_m=0.0), section, a, io)
    assert abs(dual - c_true) <= 1.0, (dual, c_true)
    assert abs(point - c_true) >= abs(dual - c_true) + 1.0, (point, dual, c_true)

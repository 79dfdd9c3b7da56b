"""The merges' hand-over where SUMO's lane changer makes a change for the route urgent
(``deploy.drivers.strategic_reach_m``, LC2013's strategic look-ahead), from SUMO's best
lanes (``Simulation.lane_end``: the distance and the lane changes needed). On drawn 501
(lanes 4-2-1-1-4) only m0's lane 3 carries on to the end: a driver on lane 0 needs three
changes to the left, which at the limit (24.1 m/s) SUMO's drivers make urgent 1,491 m
before the drop, the whole 598 m edge; the fixed 400 m it replaces commanded their
speeds for its first 198 m (hU, stop 34: 125 m on m0, 23.4 m/s deployed against the
truth's 15.5)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
from conftest import ROOT

from macromicro_sumo.deploy.lane_change import (
    LC_LOOKAHEAD_MEMORY,
    lookahead_speeds,
    strategic_reach_m,
)
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

sys.path.insert(0, str(ROOT / "scripts"))
_spec = importlib.util.spec_from_file_location(
    "bench_hidden_count", ROOT / "scripts" / "bench_hidden_count.py"
)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_lane_changes_to_the_route_from_sumo_best_lanes(tmp_path: Path) -> None:
    """SUMO on drawn 501: a car 10 m into each lane of the 4-lane entry edge m0. Lanes 0
    and 1 end with m0 (597.8 m), lane 2 leads onto m1's lane 0, which ends with m1
    (1,068 m on), lane 3 carries on: 3, 2, 1 and 0 changes to the left."""
    bench.build_network(tmp_path, 501)
    net = next(tmp_path.rglob("*.net.xml"))
    sim = Simulation(SumoOptions(net, (), 0.5, 1))
    try:
        sim.add_route("main", ["m0", "m1", "m2", "m3", "m4"])
        ids = [f"v{ln}" for ln in range(4)]
        for ln, vid in enumerate(ids):
            sim.add_vehicle(vid, "main", "DEFAULT_VEHTYPE", ln, 10.0, 0.0)
        sim.step()
        lanes, pos, _ = sim.lane_states(ids)
        got = [sim.lane_end(v, ln, p) for v, ln, p in zip(ids, lanes, pos, strict=True)]
    finally:
        sim.close()
    assert [o for _, o in got] == [3, 2, 1, 0], got
    ends = np.array([d for d, _ in got])
    np.testing.assert_allclose(ends[:2] + pos[:2], 597.8, atol=0.1)
    assert 1060.0 < ends[2] < 1075.0 and np.isinf(ends[3]), ends
    # LC2013 at the limit, a 5 m car with minGap 2.5: laDist 24.1 x 10 x 2 + 15 = 497 m a
    # change to the left; no change needed: never handed over.
    offsets = np.array([3.0, 2.0, 1.0, 0.0])
    reach = strategic_reach_m(offsets, np.full(4, 24.1), np.full(4, 7.5))
    np.testing.assert_allclose(reach, [1491.0, 994.0, 497.0, 0.0])
    # Where the cars on lanes 0 and 1 are (588 m before the drop) SUMO's drivers change
    # urgently: handed over; the fixed 400 m commanded them there. Lane 2's is not yet.
    assert np.all(ends[:2] <= reach[:2]) and np.all(ends[:2] > 400.0)
    assert ends[2] > reach[2]
    # A change to the right reaches half as far (lcLookaheadLeft 2 is the left's).
    right = strategic_reach_m(np.array([-1.0]), np.array([10.0]), np.array([7.5]))
    np.testing.assert_allclose(right, [115.0])


def test_the_lookahead_speed_rises_at_once_and_decays_with_memory() -> None:
    """``lookahead_speeds``: none yet (NaN) or a faster vehicle takes its speed, a slower
    one decays towards it with memory 0.9/s; bit for bit the values of the expression it
    replaced in ``SectionSpeedDriver.handover_m`` (isnan(la) | (v > la)), over random
    speeds with ties, NaNs, zeros and -0.0."""
    rng = np.random.default_rng(3)
    la = rng.uniform(0.0, 40.0, 400)
    v = rng.uniform(0.0, 40.0, 400)
    la[::7] = np.nan
    v[::11] = la[::11]  # ties
    la[5::13], v[6::13] = 0.0, -0.0
    got = lookahead_speeds(la, v, 0.5)
    keep = 1.0 - (1.0 - LC_LOOKAHEAD_MEMORY) * 0.5
    old = np.where(np.isnan(la) | (v > la), v, keep * la + (1.0 - keep) * v)
    assert got.tobytes() == old.tobytes()
    small = lookahead_speeds(np.array([np.nan, 10.0, 30.0]), np.array([20.0, 20.0, 20.0]), 0.5)
    np.testing.assert_allclose(small, [20.0, 20.0, 0.95 * 30.0 + 0.05 * 20.0])

"""scripts/bench_leaders.py: SUMO's getLeader of a vehicle with another ahead on its lane
is that vehicle, its gap (back - position - minGap) equal to the bit to the one the
script computes from the step's states; the front vehicle has none, and one behind a
vehicle on the next edge is first on its lane (SUMO looks on)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from conftest import ROOT, line_net

from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

_spec = importlib.util.spec_from_file_location(
    "bench_leaders", ROOT / "scripts" / "bench_leaders.py"
)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def test_same_lane_leaders_are_getleaders_to_the_bit(tmp_path: Path) -> None:
    net = line_net(tmp_path, (300.0, 1000.0), 1, 30.0)
    sim = Simulation(SumoOptions(net, (), 0.5, 0))
    try:
        sim.add_route("r", ["A", "B"])
        # back to front: c behind b behind a on A; d on B, ahead of a (a is first on A)
        for vid, pos, v in (("c", 50.3, 9.7), ("b", 120.1, 11.3), ("a", 201.7, 12.9)):
            sim.add_vehicle(vid, "r", "DEFAULT_VEHTYPE", 0, pos, v)
        sim.add_route("rb", ["B"])
        sim.add_vehicle("d", "rb", "DEFAULT_VEHTYPE", 0, 40.0, 13.0)
        for _ in range(3):
            sim.step()
        st = sim.vehicle_states()
        vids = ["a", "b", "c", "d"]
        got = sim.leaders(vids, 250.0)
        shape = {v: sim.vtype_shape(sim.vehicle_type(v))[:2] for v in st.ids}
        kinds = script.classify(st, vids, got, shape)
    finally:
        sim.close()
    assert [g[0] for g in got] == ["d", "a", "b", ""], got
    assert kinds == {"same_lane_bit_equal": 2, "first_on_lane": 1, "none": 1}, kinds
    rows = np.fromiter(map(st.index.__getitem__, vids), np.int64, 4)
    length = np.array([shape[v][0] for v in st.ids])
    min_gap = np.array([shape[v][1] for v in st.ids])
    lead, gap = script.same_lane_leaders(st, rows, length, min_gap)
    assert [st.ids[j] if j >= 0 else "" for j in lead.tolist()] == ["", "a", "b", ""]
    assert gap[1] == got[1][1] and gap[2] == got[2][1]  # to the bit
    assert np.isnan(gap[[0, 3]]).all()

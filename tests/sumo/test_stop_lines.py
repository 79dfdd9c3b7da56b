"""``Simulation.stop_lines``: the one query of the red lines ahead (the deployment's, the
demand env's and the snapshot env's), on real SUMO nets."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import sumo
from conftest import one_phase_program, stop_offset_net

from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.stop_offsets import lane_stop_offsets

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


def test_a_red_link_from_another_lane_is_not_the_vehicles_own(tmp_path: Path) -> None:
    """game/cross, link 7 (1si_1, through) red, link 6 (1si_0, right) green: SUMO gives
    "thr0" (through on 1si_0) and "thr1" (through on 1si_1) link 7's red at their lanes'
    end, "up" (through on 1fi, whose best lanes go on to 1si_1) too, 181.18 m ahead.
    Only thr0's is not its own: ``stop_lines_m`` is inf for it (it stops at its lane's
    end), the line itself for the others; "rgt" (right turn, link 6 green) has none."""
    state = ["r"] * 12
    state[6] = "G"
    sim = Simulation(
        SumoOptions(CROSS, (one_phase_program(tmp_path, "0", "".join(state)),), 0.5, 1)
    )
    ids = ["thr0", "thr1", "up", "rgt"]
    try:
        sim.add_route("thr", ["1si", "2o"])
        sim.add_route("upthr", ["1fi", "1si", "2o"])
        sim.add_route("rgt", ["1si", "3o"])
        places = [("thr", 0, 20.0), ("thr", 1, 20.0), ("upthr", 0, 5.0), ("rgt", 0, 60.0)]
        for vid, (route, lane, pos) in zip(ids, places, strict=True):
            sim.add_vehicle(vid, route, "DEFAULT_VEHTYPE", lane, pos, 10.0)
        sim.set_lane_change_mode(ids, 0)
        sim.step()
        lines = sim.stop_lines(ids)
        line_m = sim.stop_lines_m(ids)
        lanes, pos, _ = sim.lane_states(ids)
        empty = sim.stop_lines([]), sim.stop_lines_m([])
    finally:
        sim.close()
    assert lanes[:3] == ["1si_0", "1si_1", "1fi_0"]
    assert lines.lanes == ["1si_1", "1si_1", "1si_1", ""]
    assert lines.own.tolist()[:3] == [False, True, True]
    np.testing.assert_allclose(lines.dist_m[:2], 135.75 - pos[:2], atol=1e-6)
    assert lines.dist_m[3] == np.inf and not lines.offset_m.any()
    assert line_m[0] == np.inf and line_m[3] == np.inf
    np.testing.assert_array_equal(line_m[1:3], lines.dist_m[1:3])
    # stop_lines_m's plain floats: StopLines.line_m's values bit for bit (NaN none here)
    assert line_m.tobytes() == lines.line_m(1.0).tobytes()
    assert empty[0].dist_m.shape == empty[1].shape == (0,) and empty[0].lanes == []
    stop = lines.stop_m(1.0)
    assert stop[0] == np.inf and np.allclose(stop[1:3], lines.dist_m[1:3] - 1.0)


def test_a_lanes_stop_offset_is_read_from_the_net(tmp_path: Path) -> None:
    """netconvert writes A's stopOffset on the edge and lane 1's on the lane; the lane's
    replaces the edge's. A passenger car on A_0 reads 3 m, on A_1 6 m, a bus on A_1 none
    (lane 1's names only passenger cars). ``stop_lines_m`` moves the line upstream by what
    the offset adds to the vType's jmStoplineGap (1 m; 5 m for "far": 3 m on A_0, none
    beyond its own 5 m), so that the line less that gap is where SUMO stops it
    (max(jmStoplineGap, stopOffset) before the line, measured in
    tests/deploy/test_stop_line_lanes.py)."""
    net = stop_offset_net(tmp_path)  # A: stopOffset 3 m, A_1's own 6 m (passenger)
    got = lane_stop_offsets(net)
    assert set(got) == {"A_0", "A_1"}
    assert got["A_0"].value_m == 3.0 and got["A_0"].applies("bus")
    assert got["A_1"].value_m == 6.0 and got["A_1"].applies("passenger")
    assert not got["A_1"].applies("bus")
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        '<routes>\n    <vType id="bus" vClass="bus"/>\n    <vType id="far" jmStoplineGap="5"/>\n'
        '    <route id="r" edges="A B"/>\n</routes>\n'
    )
    opts = SumoOptions(
        net, (one_phase_program(tmp_path, "tl", "rrrr"),), 0.5, 1, route_files=(routes,)
    )
    sim = Simulation(opts)
    ids = ["c0", "c1", "b1", "f0"]
    try:
        places = [("DEFAULT_VEHTYPE", 0, 50.0), ("DEFAULT_VEHTYPE", 1, 50.0)]
        places += [("bus", 1, 150.0), ("far", 0, 150.0)]
        for vid, (vtype, lane, pos) in zip(ids, places, strict=True):
            sim.add_vehicle(vid, "r", vtype, lane, pos, 10.0)
        sim.set_lane_change_mode(ids, 0)
        sim.step()
        lines = sim.stop_lines(ids)
        line_m = sim.stop_lines_m(ids)
    finally:
        sim.close()
    assert lines.own.all() and lines.lanes == ["A_0", "A_1", "A_1", "A_0"]
    np.testing.assert_array_equal(lines.offset_m, [3.0, 6.0, 0.0, 3.0])
    np.testing.assert_allclose(line_m, lines.dist_m - [2.0, 5.0, 0.0, 0.0])
    assert line_m.tobytes() == lines.line_m(np.array([1.0, 1.0, 1.0, 5.0])).tobytes()
    np.testing.assert_allclose(lines.stop_m([1.0, 1.0, 1.0, 5.0]), lines.dist_m - [3, 6, 1, 5])


def test_a_net_written_again_at_the_same_path_is_read_again(tmp_path: Path) -> None:
    """``lane_stop_offsets`` reads a file once, and again where it changed: a net without
    stopOffset, then one with, written to the same path (a pipeline that builds its net
    again in one process). Before: the first read's empty answer stood."""
    net = stop_offset_net(tmp_path)
    text = net.read_text()
    plain = re.sub(r"\s*<stopOffset[^>]*/>", "", text)
    net.write_text(plain)
    assert lane_stop_offsets(net) == {}
    net.write_text(text)
    assert set(lane_stop_offsets(net)) == {"A_0", "A_1"}

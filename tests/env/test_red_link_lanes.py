"""A red point on the lane of the red link, SUMO's own (hS's and hQ's "wrong red", case b).

game/cross, 1si: lane 0 turns right (link 6), lane 1 goes through (link 7). With link 6
green and link 7 red, SUMO gives a car routed through on lane 0 (lane changes off) the red
of link 7, whose lane is 1si_1. The snapshot env (``SectionCore._scene``) made each
vehicle's red a stop point on the lane it reaches along the connections, its own lane 0:
the right turner ahead of it on lane 0 then read a red line at a green light.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import sumo

from macromicro_sumo.env.section_observations import section_observations, stop_points
from macromicro_sumo.road.section import STOP, read_section
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
EDGES = ["1fi", "1si", "2o", "2fo"]
VTYPE = "DEFAULT_VEHTYPE"  # 5 m long, minGap 2.5 m


def test_a_red_link_puts_its_stop_point_on_its_own_lane(tmp_path: Path) -> None:
    """thr0 (through, on 1si_0, lane changes off) 20 m in, rgt0 (right turn) 60 m in on
    the same lane, thr1 (through) on 1si_1: SUMO gives thr0 and thr1 link 7's red on
    1si_1 and rgt0 link 6's green. The stop points are one, on lane 1 at 1si's end; rgt0
    sees no standing leader (its own route leaves the section there), thr1 the red line.
    Before: a second point on lane 0, and rgt0 read a red line there (a standing
    leader at 82.25 m, not 250 m: none)."""
    state = ["r"] * 12
    state[6] = "G"
    add = tmp_path / "b.add.xml"
    add.write_text(
        '<additional>\n    <tlLogic id="0" type="static" programID="b" offset="0">\n'
        f'        <phase duration="10000" state="{"".join(state)}"/>\n'
        "    </tlLogic>\n</additional>\n"
    )
    cross = read_section(CROSS, EDGES, closed=False)
    sim = Simulation(SumoOptions(CROSS, (add,), 0.5, 1))
    ids = ["thr0", "rgt0", "thr1"]
    try:
        sim.add_route("thr", ["1si", "2o"])
        sim.add_route("rgt", ["1si", "3o"])
        places = [("thr", 0, 20.0), ("rgt", 0, 60.0), ("thr", 1, 20.0)]
        for vid, (route, lane, pos) in zip(ids, places, strict=True):
            sim.add_vehicle(vid, route, VTYPE, lane, pos, 10.0)
        sim.set_lane_change_mode(ids, 0)
        sim.step()
        lanes, pos, speed = sim.lane_states(ids)
        lines = sim.stop_lines(ids)
        dist, links = lines.dist_m, lines.lanes
    finally:
        sim.close()
    assert lanes == ["1si_0", "1si_0", "1si_1"] and links == ["1si_1", "", "1si_1"]
    assert np.isfinite(dist[[0, 2]]).all() and dist[1] == np.inf
    at = [cross.locate(ln, p) for ln, p in zip(lanes, pos, strict=True)]
    lane, arc = np.array([a[0] for a in at]), np.array([a[1] for a in at])
    stop_lane, stop_arc = stop_points(cross, lane, arc, dist, links)
    end = float(cross.offsets_m[1] + cross.lengths_m[1])
    assert stop_lane.tolist() == [1] and np.allclose(stop_arc, [end])
    on, driven = np.ones(3, dtype=bool), np.array([True, False, True])
    five = np.full(3, 5.0)
    obs, leader, _ = section_observations(
        cross, lane, arc, speed, on, "lookahead", stop_lane, stop_arc, None, five, driven
    )
    assert leader[1] != STOP, obs[1, 2]
    assert leader[2] == STOP and abs(obs[2, 2] - (end - arc[2] - 1.0 + 2.5 + 5.0)) < 0.1

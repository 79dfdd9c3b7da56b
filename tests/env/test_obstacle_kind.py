"""What stands ahead is a red line or a lane's end as ``road.leaders.section_ahead`` finds
it, not as the stop points' lane index and arc suggest (``env.section_observations``).

Past an on-ramp the through lanes' indices shift by one: a car on A's lane 0 drives on
onto B's lane 1, and B ends at a red light. Real SUMO stops the car 1 m (jmStoplineGap)
before the line; the observation taken upstream on A must place its standing leader so
that a reader's gap (spacing - length - minGap) ends where SUMO stops it. Before (stop
34), the envs matched a stop point by the vehicle's own lane index: the micro pairs' stop
points (every lane of B) read as a lane's end, 1 m too far, and SectionCore's point (the
car's own index, 0, B's added lane) was not ahead of it at all (a free road).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import netconvert

from macromicro_sumo.env.section_observations import (
    lane_reached,
    section_observations,
    stop_points,
)
from macromicro_sumo.road.leaders import AHEAD_END, AHEAD_NONE, AHEAD_RED, section_ahead
from macromicro_sumo.road.section import Section, read_section
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

VTYPE = "DEFAULT_VEHTYPE"  # 5 m long, minGap 2.5 m


def lanes_light(folder: Path, a_lanes: int, b_lanes: int, a_onto_b: dict[int, int]) -> Path:
    """A (``a_lanes``, 200 m) -> B (``b_lanes``, 200 m; A's lane i onto B's ``a_onto_b[i]``)
    -> a traffic light that stays red -> C (as many lanes as B); the net, and beside it
    ``red.add.xml``, the red program."""
    nodes = "\n".join(
        [
            '<node id="n0" x="0" y="0"/>',
            '<node id="n1" x="200" y="0"/>',
            '<node id="tl" x="400" y="0" type="traffic_light"/>',
            '<node id="n3" x="600" y="0"/>',
        ]
    )
    edges = "\n".join(
        [
            f'<edge id="A" from="n0" to="n1" numLanes="{a_lanes}" speed="15"/>',
            f'<edge id="B" from="n1" to="tl" numLanes="{b_lanes}" speed="15"/>',
            f'<edge id="C" from="tl" to="n3" numLanes="{b_lanes}" speed="15"/>',
        ]
    )
    cons = [
        f'<connection from="A" to="B" fromLane="{i}" toLane="{j}"/>' for i, j in a_onto_b.items()
    ]
    cons += [f'<connection from="B" to="C" fromLane="{i}" toLane="{i}"/>' for i in range(b_lanes)]
    net = netconvert(folder, nodes, edges, "\n".join(cons))
    (folder / "red.add.xml").write_text(
        '<additional>\n    <tlLogic id="tl" type="static" programID="red" offset="0">\n'
        f'        <phase duration="10000" state="{"r" * b_lanes}"/>\n    </tlLogic>\n'
        "</additional>\n"
    )
    return net


# An on-ramp's added lane (A's lanes onto B's 1 and 2), and a lane drop (A's lane 0 ends,
# its lanes 1 and 2 onto B's 0 and 1): the car on A's lane 0, and on A's lane 2.
NETS = {"ramp": (2, 3, {0: 1, 1: 2}, 0), "drop": (3, 2, {1: 0, 2: 1}, 2)}


@pytest.fixture(scope="module", params=sorted(NETS))
def ramp(request, tmp_path_factory: pytest.TempPathFactory) -> tuple[Section, Path, int]:
    a, b, cons, car_lane = NETS[request.param]
    net = lanes_light(tmp_path_factory.mktemp(request.param), a, b, cons)
    return read_section(net, ["A", "B", "C"], closed=False), net, car_lane


def test_the_kind_is_what_was_found(ramp) -> None:
    """``section_ahead`` says a red line where a stop point given is the obstacle (the car
    meets the point on the lane it reaches on B), nothing where none is ahead (no point on
    that lane), a lane's end where its lane leads nowhere (B's lanes cut off from C)."""
    section, _, car_lane = ramp
    end_b = float(section.offsets_m[1] + section.lengths_m[1])
    lane, arc = np.array([car_lane]), np.array([50.0])
    reached = int(lane_reached(section, np.array([0]), lane, np.array([1]))[0])
    others = np.array([i for i in range(int(section.n_lanes[1])) if i != reached])
    for points, want in (([reached], AHEAD_RED), (others, AHEAD_NONE)):
        _, gap, kind = section_ahead(
            section, lane, arc, np.array(points), np.full(len(points), end_b)
        )
        assert kind[0] == want
    np.testing.assert_allclose(
        section_ahead(section, lane, arc, [reached], [end_b])[1], end_b - 50.0
    )
    ends = section.lane_ends.copy()
    ends[1, : section.n_lanes[1]] = True
    cut = dataclasses.replace(section, lane_ends=ends)
    _, gap, kind = section_ahead(cut, lane, arc)
    assert kind[0] == AHEAD_END and gap[0] == pytest.approx(end_b - 50.0)


def test_a_red_line_past_a_lane_change_of_index_is_where_sumo_stops(ramp) -> None:
    """The car 170 m into A: SectionCore's observation (its own red line from SUMO,
    ``stop_points``) and the micro pairs' (a stop point on every lane of B) put the standing
    leader where SUMO then stops the car, 1 m before the line, within 0.1 m."""
    section, net, car_lane = ramp
    sim = Simulation(SumoOptions(net, (net.parent / "red.add.xml",), 0.5, 1))
    try:
        sim.add_route("r", ["A", "B", "C"])
        sim.add_vehicle("car", "r", VTYPE, car_lane, 170.0, 10.0)
        sim.step()
        sim.set_lane_change_mode(["car"], 0)
        lanes, pos, speed = sim.lane_states(["car"])
        dist = np.fmin(sim.stop_lines_m(["car"]), np.inf)
        for _ in range(240):
            sim.step()
        lanes_end, pos_end, speed_end = sim.lane_states(["car"])
    finally:
        sim.close()
    assert lanes[0] == f"A_{car_lane}" and lanes_end[0].startswith("B_") and speed_end[0] < 0.01
    ln, s = section.locate(lanes[0], float(pos[0]))
    stands = section.locate(lanes_end[0], float(pos_end[0]))[1]
    end_b = float(section.offsets_m[1] + section.lengths_m[1])
    assert stands == pytest.approx(end_b - 1.0, abs=0.05)
    lane, arc, one = np.array([ln]), np.array([s]), np.ones(1, dtype=bool)
    b_lanes = int(section.n_lanes[1])
    every = (np.arange(b_lanes), np.full(b_lanes, end_b))  # the micro pairs' (data.section)
    for points, route in ((stop_points(section, lane, arc, dist), one), (every, None)):
        obs, _, _ = section_observations(
            section, lane, arc, speed, one, "paper", *points, None, np.array([5.0]), route
        )
        assert s + obs[0, 2] - 5.0 - 2.5 == pytest.approx(stands, abs=0.1)

"""The end of a lane that does not continue along the section is a standing leader in the
Stage II envs' observation of a driven vehicle (``Section.route_ends``, the generator's
``scene_stops`` too).

SUMO's game/cross with its west approach as the section: 1si has three lanes, of which only
lane 1 links onto 2o; lanes 0 and 2 turn right and left. A vehicle the env drives keeps the
section's route, and SUMO stops one that has not left a turning lane at its end. Before,
the envs' observation ended only lanes with no connection at all: a vehicle on 1si's
left-turn lane saw a free road. A recorded vehicle drives its own route (a turner leaves
the section there): its observation (the micro pairs) keeps the free road.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sumo

from macromicro_sumo.env.section_observations import section_observations
from macromicro_sumo.generator.section_scene import scene_stops
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.section import NO_LEADER_GAP_M, STOP, Section, read_section
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
EDGES = ["1fi", "1si", "2o", "2fo"]


@pytest.fixture(scope="module")
def cross() -> Section:
    return read_section(CROSS, EDGES, closed=False)


def sumo_lane_ends(net: Path, edges: list[str], places, section: Section, leader_of=None):
    """Vehicles placed in SUMO at ``places`` (edge index, lane, position), each on the
    section's route from its edge, after one step: their lanes, the section's lane and arc
    of each, their speeds, SUMO's distance to where each must leave its lane
    (``Simulation.lane_end_m``) and, for ``leader_of``'s index, SUMO's leader within 800 m."""
    sim = Simulation(SumoOptions(net, (), 0.5, 1))
    try:
        for e in range(len(edges)):
            sim.add_route(f"from{e}", edges[e:])
        ids = [f"v{i}" for i in range(len(places))]
        for vid, (e, ln, pos) in zip(ids, places, strict=True):
            sim.add_vehicle(vid, f"from{e}", "DEFAULT_VEHTYPE", ln, pos, 0.0)
        sim.step()
        lanes, pos, speed = sim.lane_states(ids)
        want = np.array(
            [sim.lane_end_m(v, ln, p) for v, ln, p in zip(ids, lanes, pos, strict=True)]
        )
        leader = (
            None if leader_of is None else sim.leaders(ids[leader_of : leader_of + 1], 800.0)[0][0]
        )
    finally:
        sim.close()
    at = [section.locate(ln, p) for ln, p in zip(lanes, pos, strict=True)]
    lane = np.array([a[0] for a in at])
    arc = np.array([a[1] for a in at])
    return ids, lanes, lane, arc, speed, want, leader


def test_a_turning_lanes_end_is_a_standing_leader(cross: Section) -> None:
    """Driven vehicles 40 m before 1si's end on each of its lanes: on the turning lanes (0,
    2) the lane's end is a standing leader 40 m ahead (delta v = own speed); the through
    lane (1) sees a free road on 2o. Recorded vehicles there (turners) see a free road.
    The generator's standing obstacles are the same ends."""
    end = float(cross.offsets_m[1] + cross.lengths_m[1])
    lane, arc = np.array([0, 1, 2]), np.full(3, end - 40.0)
    speed = np.array([8.0, 9.0, 10.0])
    on = np.ones(3, dtype=bool)
    obs, leader, _ = section_observations(cross, lane, arc, speed, on, "lookahead", on_route=on)
    np.testing.assert_array_equal(leader, [STOP, -1, STOP])  # no vehicle ahead
    np.testing.assert_allclose(obs[:, 2], [40.0, NO_LEADER_GAP_M, 40.0])  # spacing
    np.testing.assert_allclose(obs[:, 3], [8.0, 0.0, 10.0])  # delta v
    np.testing.assert_array_equal(
        section_leaders(cross, lane, arc, None, None, on)[0], [STOP, -1, STOP]
    )
    # Recorded vehicles (no ``on_route``), one driven among them (lane 2).
    obs, _, _ = section_observations(cross, lane, arc, speed, on, "lookahead")
    np.testing.assert_allclose(obs[:, 2], NO_LEADER_GAP_M)
    mixed = section_leaders(cross, lane, arc, None, None, np.array([False, False, True]))
    np.testing.assert_array_equal(mixed[0], [-1, -1, STOP])
    assert not cross.lane_ends.any()  # every lane of the section leads somewhere
    np.testing.assert_array_equal(cross.route_ends, [[0, 0, 0], [1, 0, 1], [0, 0, 0], [0, 0, 0]])

    class NoLights:
        stop_arc_m = None

        def __len__(self) -> int:
            return 1

    st_lane, st_arc = scene_stops(cross, NoLights())  # type: ignore[arg-type]
    assert sorted(zip(st_lane[0].tolist(), st_arc[0].tolist(), strict=True)) == [
        (0, pytest.approx(end)),
        (2, pytest.approx(end)),
    ]


def test_lanes_end_where_sumo_makes_the_sections_route_leave_them(cross: Section) -> None:
    """In SUMO, vehicles on the section's route on every lane of 1fi, 1si and 2o: the env's
    observation of them (driven) has a standing leader exactly where SUMO's best lanes say the vehicle must
    leave its lane (``Simulation.lane_end_m``, the deployment's and the demand env's
    source), at the distance SUMO gives (within 0.5 m: the lanes' own lengths differ
    from the section's arc), and none elsewhere."""
    places = [(0, 0, 100.0), (1, 0, 30.0), (1, 1, 30.0), (1, 2, 30.0), (2, 0, 100.0)]
    ids, lanes, lane, arc, speed, want, _ = sumo_lane_ends(CROSS, EDGES, places, cross)
    assert sorted(set(lanes) & {"1si_0", "1si_2"}) == ["1si_0", "1si_2"]
    on = np.ones(len(ids), dtype=bool)
    obs, _, _ = section_observations(cross, lane, arc, speed, on, "lookahead", on_route=on)
    lead, _ = section_leaders(cross, lane, arc, on_route=on)
    must_leave = np.isfinite(want)
    assert must_leave.sum() == 2
    np.testing.assert_array_equal(lead == STOP, must_leave)
    np.testing.assert_allclose(obs[must_leave, 2], want[must_leave], atol=0.5)


NETGEN = Path(__file__).resolve().parents[2] / "sumo_nets" / "netgen_corridor" / "corridor.net.xml"
NETGEN_EDGES = [f"e{i}" for i in range(7)]


def test_a_lane_leading_only_onto_ending_lanes_ends_where_they_end() -> None:
    """netgen_corridor's e4 lane 0 leads only onto e5 lanes 0 and 1, which both end: SUMO
    makes a vehicle there leave it (its best lanes), at the end of e5's lanes. The envs'
    observation, of a driven vehicle and of a recorded one alike (both lanes lead
    nowhere), has its standing leader there, at SUMO's distance along the road
    (``Simulation.lane_end_m``, the deployment's and the demand env's source; within 0.5 m),
    and so for the lanes that end themselves; e4 lane 1 (onto e5 lane 2) carries on.
    Before, the envs saw e4 lane 0's end only from e5 on: a free road (SUMO: 700 m to go,
    of which 8 m of junction its best lanes leave out)."""
    sec = read_section(NETGEN, NETGEN_EDGES, closed=False)
    places = [(4, 0, 100.0), (4, 1, 100.0), (5, 1, 50.0), (2, 0, 100.0), (0, 0, 100.0)]
    ids, lanes, lane, arc, _, want, sumo_leader = sumo_lane_ends(
        NETGEN, NETGEN_EDGES, places, sec, leader_of=0
    )
    assert lanes == ["e4_0", "e4_1", "e5_1", "e2_0", "e0_0"]
    # e4 lane 0's end is beyond e5_1's vehicle: alone, on its own (the others stay).
    alone = np.array([0, 1, 3, 4])
    must_leave = np.isfinite(want[alone])
    np.testing.assert_array_equal(must_leave, [True, False, True, True])
    end_of_e5 = float(sec.offsets_m[5] + sec.lengths_m[5])
    np.testing.assert_allclose(want[0], end_of_e5 - arc[0], atol=0.5)  # along the road
    for on_route in (np.ones(len(alone), dtype=bool), None):
        lead, gap = section_leaders(sec, lane[alone], arc[alone], on_route=on_route)
        np.testing.assert_array_equal(lead == STOP, must_leave)
        np.testing.assert_allclose(gap[must_leave], want[alone][must_leave], atol=0.5)
    # With e5_1's vehicle, it is e4 lane 0's leader (before its lane's end), as in SUMO.
    lead, _ = section_leaders(sec, lane, arc)
    assert lead[0] == 2
    assert sumo_leader == ids[2]

"""One observation of what is ahead in the Stage II envs, the demand env and the deployment.

A red or yellow stop line and the end of a lane a vehicle must leave are standing leaders
(``road.leaders.standing_spacing_m``): a standing vehicle of the own length whose back is
minGap (2.5 m) beyond where SUMO stops the front, 1 m before a red line (jmStoplineGap), at
a lane's end, so that every reader of the spacing takes SUMO's gap to the stop. The
snapshot env reads it on the section's arc (``section_observations`` with ``stop_points``
and the vehicles' lengths, as ``SectionCore._scene``), the deployment (``deploy.observe.
observe_rows``, as ``deploy.drivers`` composes it) and the demand env (``env.demand.
sumo_observations``, as ``DemandCore._stops``) from SUMO's state. Before (3e1f4d0), the
envs, in which the policy trains, gave the distance alone: 5 m less than the deployment.

SUMO's game/cross, its west approach as the section (1si: right-turn lane 0, through lane
1, left-turn lane 2, of which only lane 1 links onto 2o), one SUMO state per signal phase.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sumo

from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table, observe_rows
from macromicro_sumo.env.demand import sumo_observations
from macromicro_sumo.env.section_observations import section_observations, stop_points
from macromicro_sumo.road.leaders import nearer_standing, standing_spacing_m, stop_distance_m
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section, read_section
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
EDGES = ["1fi", "1si", "2o", "2fo"]
VTYPE = "DEFAULT_VEHTYPE"  # 5 m long, minGap 2.5 m
# (section edge, lane, metres before the edge's end; on 2o: from its start) of each vehicle:
# the first on the through lane, one behind it, one on each turning lane, one past the
# junction.
PLACES = [(1, 1, 30.0), (1, 1, 50.0), (1, 0, 40.0), (1, 2, 60.0), (2, 0, -50.0)]
PHASES = {"green": 0, "red": 2}  # the net's program "0": phase 2 is red for 1si -> 2o


@pytest.fixture(scope="module")
def cross() -> Section:
    return read_section(CROSS, EDGES, closed=False)


def three_observations(
    cross: Section, phase: int, places: list[tuple[int, int, float]] = PLACES
) -> tuple[np.ndarray, ...]:
    """(env, deployment, demand env) observations ("lookahead") of ``places`` in one SUMO
    state, each vehicle on the section's route, with signal program "0" in ``phase``."""
    sim = Simulation(SumoOptions(CROSS, (), 0.5, 1))
    try:
        sim.set_signal_states([("0", "0", phase, 30.0)])
        for e in range(4):
            sim.add_route(f"from{e}", EDGES[e:])
        ids = [f"v{i}" for i in range(len(places))]
        for vid, (e, ln, back) in zip(ids, places, strict=True):
            pos = float(cross.lengths_m[e]) - back if back > 0 else -back
            sim.add_vehicle(vid, f"from{e}", VTYPE, ln, pos, 5.0)
        sim.step()
        lanes, pos, speed = sim.lane_states(ids)
        red = np.fmin(sim.stop_lines_m(ids), np.inf)  # NaN (no signal ahead): none
        lane_end = np.array([sim.lane_end_m(v, ln, 0.0) for v, ln in zip(ids, lanes, strict=True)])
        leaders = sim.leaders(ids, 250.0)
        st = sim.vehicle_states()
        shape = sim.vtype_shape(VTYPE)
    finally:
        sim.close()
    # The snapshot env (``SectionCore._scene``): its driven vehicles drive the route.
    at = [cross.locate(ln, p) for ln, p in zip(lanes, pos, strict=True)]
    lane = np.array([a[0] for a in at])
    arc = np.array([a[1] for a in at])
    on = np.ones(len(ids), dtype=bool)
    stop_lane, stop_arc = stop_points(cross, lane, arc, red)
    length = np.full(len(ids), shape[0])
    env, _, _ = section_observations(
        cross, lane, arc, speed, on, "lookahead", stop_lane, stop_arc, None, length, on
    )
    # The deployment (``Driver.observe``): lane ends from the lane's start, less the position.
    rows = np.array([st.index[v] for v in ids])
    shapes = Table.of_rows(dict.fromkeys(ids, shape), STANDING)
    stop = stop_distance_m(lane_end - st.pos_m[rows], red)
    deploy = observe_rows(
        LaneTable(cross), "lookahead", ids, rows, lanes, st, leaders, shapes, stop
    )
    # The demand env (``DemandCore._stops``).
    states = {v: (ln, p, s, 0.0) for v, ln, p, s in zip(ids, lanes, pos, speed, strict=True)}
    demand = sumo_observations(
        "lookahead",
        cross,
        ids,
        states,
        dict(zip(ids, leaders, strict=True)),
        dict.fromkeys(ids, shape),
        stop_distance_m(lane_end - pos, red),
    )
    return env, deploy[0], demand.obs


@pytest.mark.parametrize("light", sorted(PHASES))
def test_env_deployment_and_demand_env_see_the_same_ahead(cross: Section, light: str) -> None:
    """The three observations of one SUMO state agree (within 0.5 m: SUMO's lanes and the
    section's arc differ by a rounding), and the standing leaders are at SUMO's stop plus
    minGap 2.5 m and the own 5 m: at the turning lanes' ends (40 and 60 m) on green and on
    red, and at red 1 m before the first through vehicle's stop line (30 m ahead). SUMO
    gives the through vehicles on the turning lanes the through link's red, but its driver
    of them stands 0.00 m before its lane's end (measured, lane changes off), not 1 m: the
    link is not their lane's (``StopLines.own``). Before (stop 35): 1 m before the line."""
    env, deploy, demand = three_observations(cross, PHASES[light])
    np.testing.assert_allclose(deploy, env, atol=0.5)
    np.testing.assert_allclose(demand, env, atol=0.5)
    spacing = env[:, 2]
    np.testing.assert_allclose(env[2:4, 3], 5.0)  # delta v: a standing leader
    if light == "red":
        np.testing.assert_allclose(spacing[[0, 2, 3]], [36.5, 47.5, 67.5], atol=0.2)
    else:
        np.testing.assert_allclose(spacing[2:4], [47.5, 67.5], atol=0.2)  # lane ends
        assert spacing[0] > 30.0 + 50.0  # the leader is the vehicle 50 m into 2o
    np.testing.assert_allclose(spacing[1], 20.0, atol=0.5)  # the vehicle ahead


def test_a_leader_beyond_the_look_ahead_is_none_in_all_three(cross: Section) -> None:
    """A vehicle on 1fi whose leader is 390 m ahead on 2fo (green): the deployment's
    look-ahead (SUMO's leader within ``NO_LEADER_GAP_M``) sees no leader, and so does the
    env's observation (spacing 250 m, delta v 0). Before, the env observed the far leader
    (a spacing of 390 m, which the deployment never shows the policy)."""
    env, deploy, demand = three_observations(cross, PHASES["green"], [(0, 0, 35.0), (3, 0, 5.0)])
    np.testing.assert_allclose(deploy, env, atol=0.5)
    np.testing.assert_allclose(demand, env, atol=0.5)
    np.testing.assert_allclose(env[0, 2:4], [NO_LEADER_GAP_M, 0.0])


def test_standing_spacing_by_hand() -> None:
    """A red line 30 m ahead of a 5 m car: SUMO stops it 1 m before (jmStoplineGap), so its
    standing leader is at 29 + minGap 2.5 + 5 = 36.5 m, and a reader's gap (spacing -
    length - minGap) is SUMO's 29 m; a lane's end 40 m ahead (SUMO stops at it): 47.5 m;
    a front within the stop gap already: 7.5 m (gap 0). ``stop_distance_m`` takes the
    nearer of a lane end and a red line less 1 m (NaN, inf: none)."""
    np.testing.assert_allclose(
        standing_spacing_m(np.array([30.0, 40.0, 0.4]), 5.0, np.array([1.0, 0.0, 1.0])),
        [36.5, 47.5, 7.5],
    )
    stop = stop_distance_m(
        np.array([40.0, np.inf, 40.0, 3.0, 9.0]), np.array([30.0, np.inf, np.nan, 0.5, 9.5])
    )
    np.testing.assert_allclose(stop, [29.0, np.inf, 40.0, 0.0, 8.5])
    spacing = np.array([20.0, 100.0, NO_LEADER_GAP_M])
    closer = nearer_standing(spacing, np.array([29.0, 29.0, np.inf]), np.full(3, 5.0))
    np.testing.assert_array_equal(closer, [False, True, False])
    np.testing.assert_allclose(spacing, [20.0, 36.5, NO_LEADER_GAP_M])


@pytest.mark.parametrize(
    ("front_past_m", "leader_length_m", "sees_car"),
    [(2.0, 5.0, True), (13.0, 12.0, True), (6.0, 5.0, True), (7.0, 5.0, False), (30.0, 5.0, False)],
)
def test_a_vehicle_across_a_red_line_stays_its_followers_leader(
    cross: Section, front_past_m: float, leader_length_m: float, sees_car: bool
) -> None:
    """A vehicle whose front is ``front_past_m`` past 1si's red line, its tail still before
    the line or less than 1.5 m past it, is nearer than the line for the 5 m car 12 m before
    the line: SUMO's gap to it, 12 + front_past - length - minGap 2.5, is less than SUMO's
    gap to the line, 12 - jmStoplineGap 1 (the deployment's comparison, ``nearer_standing``).
    Before (stop 48; drawn arterial 1701, a Stage II evaluation collision): the stop points
    sorted by the line and the vehicles by their fronts, so the follower saw the line
    (spacing 18.5 m) and braked for it, not for the car whose tail was 9 m ahead."""
    end = float(cross.offsets_m[1] + cross.lengths_m[1])
    on = np.ones(2, dtype=bool)
    _, leader, spacing = section_observations(
        cross,
        np.array([1, 0]),
        np.array([end - 12.0, end + front_past_m]),
        np.array([4.0, 0.5]),
        on,
        "lookahead",
        np.array([1]),
        np.array([end]),
        None,
        np.array([5.0, leader_length_m]),
        on,
    )
    if sees_car:
        assert leader[0] == 1
        np.testing.assert_allclose(spacing[0], 12.0 + front_past_m)
    else:
        assert leader[0] < 0  # STOP: the line
        np.testing.assert_allclose(spacing[0], 11.0 + 2.5 + 5.0)

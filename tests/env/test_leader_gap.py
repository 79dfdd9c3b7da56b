"""``policy.observation = "lookahead_gap"``: the leader column is the bumper-to-bumper gap.

"lookahead" observes the front-to-front spacing, so behind a 12 m truck a 13 m spacing (a
1 m gap) looked like a car's 8 m gap (drawn 501, stop 35: 17 of 57 Stage II episodes with
the safety layer off ran a hidden car into an observed truck). Every observer computes the
gap the same way, against a hand computation on one real SUMO state with a truck leader:
the section env (``section_observations``), the demand env (``sumo_observations``), the
deployment (``observe_rows``, SUMO's vType length of the leader), the measured leaders of
field data; a stop point's gap is the one to where SUMO stops the car, plus its minGap, as
behind a vehicle. "lookahead" is unchanged (its column is still the spacing).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import netconvert
from section_files import routes_file, vtype

sys.path.insert(0, str(Path(__file__).parent))
from test_own_length import mixed, with_observation  # noqa: E402, F401 (a fixture)

from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table, observe_rows
from macromicro_sumo.env.demand import sumo_observations
from macromicro_sumo.env.observation import FEATURES, shift_scale
from macromicro_sumo.env.observed_drivers import observed_drivers
from macromicro_sumo.env.section_observations import section_observations
from macromicro_sumo.evaluation.micro_data import micro_pairs
from macromicro_sumo.fielddata.leaders import measured_leader_length_m, with_measured_leaders
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.road.leaders import bumper_gap_m, set_leader_gap
from macromicro_sumo.road.physics import (
    OBSERVATION_FEATURES,
    leader_length_m,
    observes_gap,
)
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

TRUCK = {"length": 12, "minGap": 2.5, "sigma": 0, "speedDev": 0}
CAR = {"length": 5, "minGap": 2.5, "sigma": 0, "speedDev": 0}
LENGTH = {"c": 5.0, "t": 12.0}


def test_the_gap_is_the_spacing_less_the_leaders_length() -> None:
    np.testing.assert_allclose(
        bumper_gap_m(np.array([30.0, NO_LEADER_GAP_M, 400.0]), np.array([12.0, 5.0, 5.0])),
        [18.0, NO_LEADER_GAP_M, NO_LEADER_GAP_M],
    )
    assert OBSERVATION_FEATURES["lookahead_gap"][2] == "gap_m"
    assert OBSERVATION_FEATURES["lookahead_gap_length"][-1] == "length_m"
    assert observes_gap("lookahead_gap") and not observes_gap("lookahead")
    # A 5 m car fleet normalises its gaps as "lookahead" its spacings.
    assert (FEATURES["spacing_m"].shift - 5.0, FEATURES["spacing_m"].scale) == (
        FEATURES["gap_m"].shift,
        FEATURES["gap_m"].scale,
    )
    assert shift_scale("lookahead_gap")[0][2] == 120.0
    # A car-following model subtracts nothing from a gap, the own length from a spacing.
    assert leader_length_m("lookahead_gap", 5.0) == 0.0
    assert leader_length_m("lookahead", 4.5) == 4.5
    # The old layouts' columns are left as they are.
    obs = np.full((1, 6), 30.0)
    assert set_leader_gap(obs, "lookahead", None) is obs and obs[0, 2] == 30.0
    with pytest.raises(ValueError, match="lengths"):
        set_leader_gap(obs, "lookahead_gap", None)


@pytest.fixture(scope="module")
def truck_state(tmp_path_factory: pytest.TempPathFactory):
    """One SUMO state on A (300 m, 1 lane) -> B (200 m): car "c" behind truck "t", read
    after one step. (net, section, lane states, leaders, shapes, lane positions)."""
    folder = tmp_path_factory.mktemp("leader_gap")
    net = netconvert(
        folder,
        '<node id="n0" x="0" y="0"/>\n<node id="n1" x="300" y="0"/>\n<node id="n2" x="500" y="0"/>',
        '<edge id="A" from="n0" to="n1" numLanes="1" speed="15"/>\n'
        '<edge id="B" from="n1" to="n2" numLanes="1" speed="15"/>',
    )
    types = routes_file(folder / "types.rou.xml", [vtype("truck", **TRUCK), vtype("car", **CAR)])
    sim = Simulation(SumoOptions(net, (), 0.5, 1, route_files=(types,)))
    try:
        sim.add_route("r", ["A", "B"])
        sim.add_vehicle("t", "r", "truck", 0, 150.0, 5.0)
        sim.add_vehicle("c", "r", "car", 0, 120.0, 8.0)
        sim.step()
        st = sim.vehicle_states()
        shapes = {"t": sim.vtype_shape("truck"), "c": sim.vtype_shape("car")}
        leaders = sim.leaders(["c", "t"], NO_LEADER_GAP_M)
        states = {v: (st.lanes[st.index[v]], *(float(a[st.index[v]]) for a in (
            st.pos_m, st.speed_mps, st.accel_mps2))) for v in ("c", "t")}  # fmt: skip
    finally:
        sim.close()
    section = read_section(net, ["A", "B"], closed=False)
    return section, st, states, leaders, shapes


def _env(section, states, observation: str, stop=None) -> np.ndarray:
    """The section env's observation of (c, t) from their arcs."""
    vids = ["c", "t"]
    lane = np.array([section.lanes[states[v][0]][1] for v in vids])
    arc = np.array([section.lanes[states[v][0]][2] + states[v][1] for v in vids])
    speed = np.array([states[v][2] for v in vids])
    stop_lane, stop_arc = (None, None) if stop is None else stop
    obs, _, _ = section_observations(
        section, lane, arc, speed, np.ones(2, bool), observation, stop_lane, stop_arc,
        length_m=np.array([LENGTH[v] for v in vids]),
    )  # fmt: skip
    return obs


def _deploy(section, st, leaders, shapes, observation: str, stop_m) -> np.ndarray:
    vids = ["c", "t"]
    rows = np.array([st.index[v] for v in vids])
    lanes = [st.lanes[r] for r in rows]
    table = Table.of_rows(shapes, STANDING)
    return observe_rows(
        LaneTable(section), observation, vids, rows, lanes, st, leaders, table, stop_m
    )[0]


def test_every_observer_sees_the_trucks_rear_not_its_front(truck_state) -> None:
    """The car behind the truck: gap = truck's position - 12 m - car's position (hand), in
    the section env, the demand env and the deployment alike; "lookahead" the spacing,
    12 m more. The truck has no leader: NO_LEADER_GAP_M in both layouts."""
    section, st, states, leaders, shapes = truck_state
    pos_c, pos_t = states["c"][1], states["t"][1]
    gap = pos_t - 12.0 - pos_c
    assert 10.0 < gap < 30.0
    no_stop = np.full(2, np.inf)
    for observation, want in (("lookahead_gap", gap), ("lookahead", gap + 12.0)):
        env = _env(section, states, observation)
        dep = _deploy(section, st, leaders, shapes, observation, no_stop)
        lead = dict(zip(["c", "t"], leaders, strict=True))
        demand = sumo_observations(
            observation, section, ["c", "t"], states, lead, shapes, no_stop
        ).obs
        for obs in (env, dep, demand):
            assert obs[0, 2] == pytest.approx(want, abs=1e-6)
            assert obs[1, 2] == NO_LEADER_GAP_M
        np.testing.assert_allclose(dep, demand, atol=1e-9)
        np.testing.assert_allclose(env, dep, atol=1e-6)
    # With the own length too: the same gap, the own length last.
    dep = _deploy(section, st, leaders, shapes, "lookahead_gap_length", no_stop)
    assert dep[0, 2] == pytest.approx(gap) and dep[:, -1].tolist() == [5.0, 12.0]


def test_a_stop_points_gap_is_where_sumo_stops_plus_the_min_gap(truck_state) -> None:
    """The truck 30 m (SUMO's gap to its stop, after jmStoplineGap 1 m) before a red line:
    its gap 30 + minGap 2.5 m, as behind a vehicle SUMO stops it minGap behind the rear;
    the deployment (``stop_m``) and the section env (a stop point 31 m ahead) agree."""
    section, st, states, leaders, shapes = truck_state
    dep = _deploy(section, st, leaders, shapes, "lookahead_gap", np.array([np.inf, 30.0]))
    assert dep[1, 2] == pytest.approx(32.5)
    line = section.lanes[states["t"][0]][2] + states["t"][1] + 31.0
    env = _env(section, states, "lookahead_gap", (np.array([0]), np.array([line])))
    assert env[1, 2] == pytest.approx(32.5)
    spacing = _env(section, states, "lookahead", (np.array([0]), np.array([line])))
    assert spacing[1, 2] == pytest.approx(32.5 + 12.0)  # a standing truck-long leader


def test_field_datas_measured_leader_takes_its_own_length() -> None:
    """A measured spacing of 30 m: behind recorded truck "t" a gap of 18 m; behind a
    leader not recorded, the recorded vehicles' median length (7 m here); "lookahead"
    keeps the spacing."""
    lengths = pd.Series([5.0, 12.0, 7.0], index=["c", "t", "x"])
    frame = pd.DataFrame(
        {
            "leader_id": ["t", "hidden"],
            "leader_spacing_m": [30.0, 30.0],
            "leader_speed_mps": [5.0, 5.0],
            "speed_mps": [8.0, 8.0],
        }
    )
    np.testing.assert_allclose(measured_leader_length_m(frame, lengths), [12.0, 7.0])
    obs = np.zeros((2, 6))
    obs[:, 2] = NO_LEADER_GAP_M
    leader = np.array([-1, -1])
    got, used = with_measured_leaders(obs, leader, frame, "lookahead_gap", lengths)
    assert used.all() and got[:, 2].tolist() == [18.0, 23.0] and got[:, 3].tolist() == [3, 3]
    old, _ = with_measured_leaders(obs, leader, frame, "lookahead", lengths)
    assert old[:, 2].tolist() == [30.0, 30.0]
    # No length known at all: the recorded scene's leader stays.
    none, used = with_measured_leaders(obs, leader, frame, "lookahead_gap", None)
    assert not used.any() and (none[:, 2] == NO_LEADER_GAP_M).all()


def test_the_gap_layout_needs_the_lengths(truck_state) -> None:
    section = truck_state[0]
    with pytest.raises(ValueError, match="length"):
        section_observations(
            section, np.zeros(1, int), np.zeros(1), np.zeros(1), np.ones(1, bool), "lookahead_gap"
        )


def test_micro_pairs_and_the_prior_take_each_leaders_length(mixed) -> None:  # noqa: F811
    """The merge with trucks (``test_own_length``'s): the micro pairs' and the Krauss
    prior's pairs' leader column is the spacing less 5 m behind a car, 12 m behind a truck;
    the prior fitted to them subtracts no length of its own (``veh_length_m`` 0), and
    "lookahead"'s pairs and prior are as they were (the spacing, the typical 5 m)."""
    sc, truth = mixed
    gap_sc = with_observation(dataclasses.replace(sc, policy=dataclasses.replace(
        sc.policy, prior="krauss")), "lookahead_gap")  # fmt: skip
    old_sc = with_observation(gap_sc, "lookahead")
    gap, acc = micro_pairs(gap_sc, truth, truth.runs)
    old, acc0 = micro_pairs(old_sc, truth, truth.runs)
    np.testing.assert_array_equal(acc, acc0)
    np.testing.assert_array_equal(np.delete(gap, 2, axis=1), np.delete(old, 2, axis=1))
    less = np.round(old[:, 2] - gap[:, 2], 6)
    assert {5.0, 12.0} <= set(np.unique(less)) <= {0.0, 5.0, 12.0}
    drivers = observed_drivers(gap_sc, truth, truth.runs)
    plain = observed_drivers(old_sc, truth, truth.runs)
    assert drivers.obs.shape == plain.obs.shape == (len(plain.obs), 4)
    less = np.round(plain.obs[:, 2] - drivers.obs[:, 2], 6)
    assert {5.0, 12.0} <= set(np.unique(less))
    prior, _, _ = fit_residual_prior(gap_sc, truth, truth.runs)
    assert prior["veh_length_m"] == 0.0
    assert fit_residual_prior(old_sc, truth, truth.runs)[0]["veh_length_m"] == 5.0

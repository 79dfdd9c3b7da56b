"""The safety layer's hand-over of a new driver's planned braking
(``deploy.brake_plan.BrakeHandover``, ``supported_decel``): a vehicle taken over from SUMO's
own model arrives at the gap that model kept; SUMO's IDM cars (decel 3.0) keep gaps
behind Krauss cars (decel 4.5) at which the layer, planning their stop at 3.0, braked them
harder than their decel at their first driven step. Real SUMO, and numpy for the bound."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import line_net
from deploy_nets import CAR
from section_files import routes_file, section_scenario
from test_safety import _run_section
from test_safety_brake import CAR_IDM, DECEL

from macromicro_sumo.deploy.brake_plan import (
    HANDOVER_DECEL_RATE_MPS2_PER_S,
    BrakeHandover,
    planned_decel,
    supported_decel,
)
from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.observe import STOP_DECEL_MPS2
from macromicro_sumo.road.physics import safe_speed
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.load import load_scenario


def test_supported_decel_is_the_least_braking_at_which_the_speed_is_safe() -> None:
    """Over seeded random states: the vType's decel where its safe speed is at least the
    speed already, where nothing is ahead and behind a standing obstacle; elsewhere the
    least b up to the moving leader's decel at which it is (within 1e-9 m/s; 1e-6 less is
    not), or that decel where even it is not."""
    rng = np.random.default_rng(41)
    n, dt = 4000, 0.5
    b = rng.choice([1.5, 3.0, 4.0, 4.5], n)
    b_l = np.where(rng.random(n) < 0.1, STOP_DECEL_MPS2, rng.choice([1.5, 3.0, 4.0, 4.5], n))
    v = rng.uniform(0.0, 35.0, n)
    v_l = np.where(b_l == STOP_DECEL_MPS2, 0.0, np.maximum(v + rng.normal(0.0, 3.0, n), 0.0))
    gap = np.where(rng.random(n) < 0.05, NO_LEADER_GAP_M, rng.uniform(0.0, 80.0, n))
    got = supported_decel(gap, v_l, v, b, b_l, dt)
    hi = planned_decel(b, b_l, "matched")
    assert np.all(got >= b) and np.all(got <= hi)
    ok_own = safe_speed(gap, v_l, b, b_l, dt) >= v
    same = ok_own | (gap >= NO_LEADER_GAP_M) | (b_l == STOP_DECEL_MPS2)
    np.testing.assert_array_equal(got[same], b[same])
    raised = got > b
    assert 200 < raised.sum() < n - 200  # both kinds are met
    at = safe_speed(gap, v_l, got, b_l, dt)
    ok_hi = safe_speed(gap, v_l, hi, b_l, dt) >= v
    inner = raised & ok_hi
    assert np.all(at[inner] >= v[inner] - 1e-9)
    below = safe_speed(gap[inner], v_l[inner], got[inner] - 1e-6, b_l[inner], dt)
    assert np.all(below < v[inner])
    np.testing.assert_array_equal(got[raised & ~ok_hi], hi[raised & ~ok_hi])


def test_the_handed_over_braking_falls_to_the_own_at_its_rate() -> None:
    """One vehicle whose arrival state asks 4.0 m/s^2 of the layer (own 3.0) and one whose
    state supports its own: the first's braking falls by the rate each step to 3.0 and
    stays there, whatever its state later; the second's is 3.0 throughout."""
    dt = 0.5
    hand = BrakeHandover(dt)
    v, v_l, b_l = np.array([20.0, 20.0]), np.array([20.0, 20.0]), np.array([4.5, 4.5])
    own = np.array([3.0, 3.0])
    g = float(np.interp(20.0, safe_speed(np.linspace(0, 60, 6001), 20.0, 4.0, 4.5, dt),
                        np.linspace(0, 60, 6001)))  # fmt: skip
    gap = np.array([g + 1e-6, 80.0])
    first = hand(np.array([0, 1]), own, b_l, gap, v, v_l, 7)
    assert abs(first[0] - 4.0) < 1e-3 and first[1] == 3.0
    step = HANDOVER_DECEL_RATE_MPS2_PER_S * dt
    for k in range(1, 8):  # later states (a gap of 0) do not restart it
        got = hand(np.array([0, 1]), own, b_l, np.zeros(2), v, v_l, 7 + k)
        np.testing.assert_allclose(got, [max(3.0, first[0] - step * k), 3.0])


def test_the_hand_over_is_decided_once_per_slot_as_the_vehicles_come_and_go() -> None:
    """Seeded random steps of driven slots (up to 900, past the arrays' first 64; vehicles
    leave and come back): each call equals a per-vehicle reference to the bit, the hand-over
    decided at a slot's first driven step alone (``supported_decel`` then; its ramp, if
    any, from that step), never again at a later return; a ramp meets both kinds."""
    dt = 0.5
    rate = HANDOVER_DECEL_RATE_MPS2_PER_S * dt
    rng = np.random.default_rng(42)
    hand = BrakeHandover(dt)
    ramps: dict[int, tuple[float, float, float]] = {}  # slot: (b at first step, step, end)
    met: set[int] = set()
    ramped = returned = 0
    for step in range(120):
        seen = 20 + 7 * step
        slots = rng.choice(min(seen, 900), size=min(rng.integers(0, 60), seen), replace=False)
        m = slots.size
        own = rng.choice([3.0, 4.0, 4.5], m)
        b_l = rng.choice([3.0, 4.5, STOP_DECEL_MPS2], m)
        gap = np.where(rng.random(m) < 0.2, NO_LEADER_GAP_M, rng.uniform(0.0, 80.0, m))
        v, v_l = rng.uniform(0.0, 30.0, m), rng.uniform(0.0, 30.0, m)
        first = supported_decel(gap, v_l, v, own, b_l, dt)
        want = own.copy()
        for i, slot in enumerate(slots.tolist()):
            if slot not in met:
                met.add(slot)
                if first[i] > own[i]:
                    end = step + float(np.ceil((first[i] - own[i]) / rate))
                    ramps[slot] = (float(first[i]), float(step), end)
            else:
                returned += 1
            if slot in ramps and ramps[slot][2] >= step:
                b0, s0, _ = ramps[slot]
                want[i] = max(own[i], b0 - rate * (step - s0))
                ramped += 1
        np.testing.assert_array_equal(hand(slots, own, b_l, gap, v, v_l, step), want)
    assert ramped > 40 and returned > 1000 and len(ramps) > 25


def _inserted_mix(folder: Path) -> Path:
    """Drawn net 502's entry: a two-lane road (limit 22.9 m/s) whose section starts where
    the vehicles are inserted (departLane free, departSpeed max), 4,000 veh/h of Krauss
    cars and IDM cars, half each: SUMO inserts each at a gap its own model accepts. 3%
    instrumented, one run of 60 + 180 s."""
    (folder / "net").mkdir(parents=True)
    net = line_net(folder / "net", (450.0, 1150.0, 1650.0), 2, 22.9)
    flow = 'type="mix" begin="0" end="3600" departLane="free" departSpeed="max"'
    routes = routes_file(
        folder / "net" / "mix.rou.xml",
        [CAR, CAR_IDM, '<vTypeDistribution id="mix" vTypes="car car_idm" probabilities="0.5 0.5"/>'],
        [f'<flow id="m" route="r" vehsPerHour="4000" {flow}/>'],
        ['<route id="r" edges="A B C"/>'],
    )  # fmt: skip
    return section_scenario(
        folder / "mix.toml",
        net,
        routes,
        ["A", "B"],
        seed=11,
        penetration=0.03,
        simulation={"warmup_s": 60.0, "duration_s": 180.0, "n_runs": 1},
        detectors={"interval_s": 60.0, "auto_spacing_m": 500.0},
        policy={"observation": "lookahead"},
    )


def test_an_idm_car_taken_over_behind_a_krauss_car_is_not_braked_hard(tmp_path: Path) -> None:
    """Krauss cars and IDM cars inserted on the section, every hidden one driven at its
    speed (an action of 0) through the layer from its first step: before the hand-over
    the layer braked 12 IDM cars (of 248 driven vehicles) at more than their decel on
    their first driven step, behind Krauss cars it planned to stop at 4.5 m/s^2 where
    they could at 3.0; now none, and none collides or teleports."""
    sc = load_scenario(_inserted_mix(tmp_path))
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B"], False)
    drv = SectionSpeedDriver(sc, section, 0, lambda obs: np.zeros(len(obs)), "sumo")
    df, stats = _run_section(sc, drv)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    driven = df[~df["observed"]].sort_values(["vehicle_id", "time_s"])
    assert driven["vehicle_id"].nunique() > 200
    # Each driven vehicle's acceleration over its first driven step: its second row.
    first = driven.groupby("vehicle_id").nth(1)
    assert (first["vtype"] == "car_idm").sum() > 80
    hard = first["accel_mps2"] < -first["vtype"].map(DECEL) - 0.01
    assert not hard.any(), (int(hard.sum()), first[hard]["vtype"].value_counts().to_dict())

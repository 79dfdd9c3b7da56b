"""Stage II holds every hidden vehicle to its vType's maxSpeed and accel, as a deployment
does, by the one rule both apply (``road.vtype.command_speeds``): SUMO applies a speed
command beyond either under the envs' speed modes, where its own models never go. Real SUMO:
a two-lane road (limit 20 m/s) whose demand is mostly vans of maxSpeed 10 with some cars of
maxSpeed 25, hidden vehicles pushed at the largest acceleration; trucks of accel 1.0 on a
road whose policy bound is 2.6 m/s^2, at full throttle in the snapshot env
(``SectionCore``) and in demand episodes (``DemandCore``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest
from conftest import line_net
from section_files import routes_file, section_scenario, vtype

from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.rollout import Rollouts, rollout
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import (
    SectionBank,
    build_section_bank,
    typical_vclass,
    typical_vtype,
)
from macromicro_sumo.env.section_envs import true_section_completion
from macromicro_sumo.road.vtype import accel_limit, command_speeds
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

VAN_MAX_MPS, CAR_MAX_MPS, LIMIT_MPS = 10.0, 25.0, 20.0
TRUCK_ACCEL, TRUCK_MAX_MPS, BOUND = 1.0, 25.0, 2.6
HORIZON = 8
TOL_MPS2 = 1e-6  # SUMO's speeds are doubles: a command applies to rounding


def _truth(folder, net, routes, **tables) -> tuple:
    """(scenario, ground truth) of the section A -> B of ``net`` with ``routes``: half
    instrumented, one run of 30 s warm-up + 60 s, the policy's bound ``BOUND``."""
    path = section_scenario(
        folder / "road.toml",
        net,
        routes,
        ["A", "B"],
        seed=3,
        penetration=0.5,
        simulation={"warmup_s": 30.0, "duration_s": 60.0, "n_runs": 1},
        detectors={"interval_s": 30.0},
        bounds={"accel_mps2": [-4.5, BOUND]},
        **tables,
    )
    sc = load_scenario(path)
    return sc, load_section_truth(simulate_section(sc, folder / "gt", progress=False), sc)


@pytest.fixture(scope="module")
def vans(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth, net): vans (maxSpeed 10) every 3 s and cars (25) every 7 s
    on two lanes of 1 km (limit 20 m/s)."""
    folder = tmp_path_factory.mktemp("section_max_speed")
    net = line_net(folder, (600.0, 1000.0), 2, LIMIT_MPS)
    common = {"length": 6, "minGap": 2.5, "accel": 2.6, "decel": 4.5, "sigma": 0, "speedDev": 0}
    routes = routes_file(
        folder / "vans.rou.xml",
        [vtype("van", **common, maxSpeed=VAN_MAX_MPS),
         vtype("car", **(common | {"length": 5}), maxSpeed=CAR_MAX_MPS)],
        ['<flow id="v" type="van" begin="0" end="90" period="3" departSpeed="5" '
         'departLane="best"><route edges="A B"/></flow>',
         '<flow id="c" type="car" begin="0" end="90" period="7" departSpeed="10" '
         'departLane="best"><route edges="A B"/></flow>'],
    )  # fmt: skip
    return (*_truth(folder, net, routes, policy={"observation": "lookahead"}), net)


@pytest.fixture(scope="module")
def trucks(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth, net): trucks (accel 1.0, maxSpeed 25) every 4 s onto a
    1.6 km lane (limit 30 m/s) at 2 m/s."""
    folder = tmp_path_factory.mktemp("env_vtype_accel")
    net = line_net(folder, (600.0, 1600.0), 1, 30.0)
    routes = routes_file(
        folder / "trucks.rou.xml",
        [vtype("truck", vClass="truck", length=12, minGap=2.5, accel=TRUCK_ACCEL, decel=4.0,
               sigma=0, maxSpeed=TRUCK_MAX_MPS, speedFactor=1, speedDev=0)],
        ['<flow id="f" type="truck" begin="0" end="90" period="4" departSpeed="2">'
         '<route edges="A B"/></flow>'],
    )  # fmt: skip
    policy = {"observation": "lookahead", "demand_horizon_s": 20.0}
    return (*_truth(folder, net, routes, policy=policy), net)


def _rollouts(road, banks: dict[str, SectionBank], accel_mps2: float) -> dict[tuple, Rollouts]:
    """Per (bank name, safety layer), a rollout of every episode of the bank in the
    snapshot env with every hidden vehicle asking for ``accel_mps2`` (of its dtype)."""
    sc, truth, net = road
    push = lambda core, obs, rng: np.full(int(core.hidden.sum()), accel_mps2)  # noqa: E731
    out = {}
    for name, bank in banks.items():
        for safety in ("none", "sumo"):
            core = SectionCore(
                sc, truth.section, bank, net, seed=0, vclass=typical_vclass(truth), safety=safety
            )
            try:
                out[name, safety] = rollout(core, push, HORIZON, 0)
            finally:
                core.close()
    return out


def _top(rollouts: dict[tuple, Rollouts], value: Callable[[Rollouts], np.ndarray], where):
    """Per key, the largest ``value`` (E, H, N) over the steps ``where(ro)`` selects; each
    selection holds more than 50 of them."""
    top = {}
    for key, ro in rollouts.items():
        sel = where(ro)
        assert np.isfinite(value(ro)[sel]).sum() > 50, key
        top[key] = float(np.nanmax(np.where(sel, value(ro), np.nan)))
    return top


def test_command_speeds_hold_each_vehicle_to_its_own_accel() -> None:
    """The one rule: a at most min(bound, vType accel); the bound alone (a scalar, the same
    float32 clipping) where no vehicle's accel is below it; maxSpeed on top."""
    v = np.array([10.0, 10.0, 24.8, 0.1])
    want = np.array([3.0, 3.0, 3.0, -9.0], dtype=np.float32)
    accel = np.array([1.0, 2.6, 1.0, 1.0])
    cmd = command_speeds(v, want, 0.5, -4.5, accel_limit(BOUND, accel), TRUCK_MAX_MPS)
    np.testing.assert_allclose(cmd, [10.5, 11.3, 25.0, 0.0])
    assert accel_limit(BOUND, np.array([2.6, np.inf])) == BOUND  # none lower: the bound
    plain = np.minimum(np.maximum(want, -4.5), BOUND)
    same = command_speeds(v, want, 0.5, -4.5, accel_limit(BOUND, np.full(4, 3.0)))
    assert np.array_equal(same, np.maximum(0.0, v + plain * 0.5))


def test_hidden_vehicles_never_exceed_their_vtypes_max_speed(vans) -> None:
    sc, truth, _ = vans
    assert typical_vtype(truth) == "van"  # the generated vehicles' vType
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_section_completion, HORIZON, 0)
    cap = bank.vmax_mps
    # Generated slots: the typical vType's; observed ones: their recorded vType's.
    assert cap is not None and (cap[bank.hidden] == VAN_MAX_MPS).all()
    assert set(np.unique(cap[bank.observed])) == {VAN_MAX_MPS, CAR_MAX_MPS}
    assert np.isinf(cap[~bank.valid]).all()
    # They also start at most at it, where the completion had them faster (the true cars).
    _, _, speed, valid, generated = (np.asarray(x) for x in true_section_completion(snaps))
    assert (speed[valid & generated] > VAN_MAX_MPS + 1.0).any()
    assert (bank.speed0_mps[bank.hidden] <= VAN_MAX_MPS + 1e-9).all()
    banks = {"capped": bank, "uncapped": dataclasses.replace(bank, vmax_mps=None)}
    hidden = lambda ro: np.broadcast_to(bank.hidden[:, None, :], ro.speed_mps.shape)  # noqa: E731
    top = _top(_rollouts(vans, banks, BOUND), lambda ro: ro.speed_mps - cap[:, None, :], hidden)
    # SUMO's speed after every step: never above the cap; without it, well above.
    assert top["capped", "none"] <= 1e-9 and top["capped", "sumo"] <= 1e-9, top
    assert top["uncapped", "none"] > 2.0 and top["uncapped", "sumo"] > 2.0, top


def test_observed_slots_accel_leaves_the_hidden_commands_as_they_were(vans) -> None:
    """Only the hidden slots' accel caps: observed slots of a lower accel (replayed) leave
    every command as without a cap, to the bit, also for a float32 action clipped at the
    bound (a per-slot float64 bound would clip it at 2.6 where the scalar gives its float32,
    2.5999999: on drawn net 300, whose trucks are observed and its hidden cars set no
    accel, training drifted from the policy it trained before)."""
    sc, truth, _ = vans
    bank = build_section_bank(
        sc, truth, section_snapshots(truth, sc, truth.runs), true_section_completion, HORIZON, 0
    )
    lower = dataclasses.replace(bank, accel_mps2=np.where(bank.hidden, np.inf, 1.0))
    banks = {"observed lower": lower, "none": dataclasses.replace(bank, accel_mps2=None)}
    ro = _rollouts(vans, banks, np.float32(3.0))
    for safety in ("none", "sumo"):
        a, b = ro["observed lower", safety], ro["none", safety]
        assert np.array_equal(a.speed_mps, b.speed_mps, equal_nan=True), safety
        assert np.array_equal(a.arc_m, b.arc_m, equal_nan=True), safety


def test_hidden_trucks_never_accelerate_beyond_their_vtype(trucks) -> None:
    sc, truth, _ = trucks
    assert typical_vtype(truth) == "truck"  # the generated vehicles' vType
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_section_completion, HORIZON, 0)
    assert bank.accel_mps2 is not None and (bank.accel_mps2[bank.valid] == TRUCK_ACCEL).all()
    banks = {"capped": bank, "uncapped": dataclasses.replace(bank, accel_mps2=None)}

    def free(ro: Rollouts) -> np.ndarray:  # below maxSpeed, where the throttle limits
        hidden = np.broadcast_to(bank.hidden[:, None, :], ro.accel_mps2.shape)
        return hidden & (ro.speed_mps < TRUCK_MAX_MPS - 1.0)

    top = _top(_rollouts(trucks, banks, 10.0), lambda ro: ro.accel_mps2, free)
    # SUMO's speed change over every step: never beyond the truck's accel; without the
    # cap, the bound's.
    assert max(top["capped", "none"], top["capped", "sumo"]) <= TRUCK_ACCEL + TOL_MPS2, top
    assert min(top["uncapped", "none"], top["uncapped", "sumo"]) > 2.0, top


def test_demand_episodes_hold_driven_trucks_to_their_accel(trucks) -> None:
    sc, truth, _ = trucks
    top = {}
    for name in ("capped", "uncapped"):
        core = DemandCore(sc, truth, truth.runs, 40)
        try:
            core.reset(int(truth.runs[0]), 35.0)
            assert {p.accel_mps2 for p in core.vtypes.values()} == {TRUCK_ACCEL}  # SUMO's
            if name == "uncapped":
                core.vtypes = {
                    k: dataclasses.replace(p, accel_mps2=np.inf) for k, p in core.vtypes.items()
                }
            rates = []
            for _ in range(40):
                vids, obs = core.observe()
                core.step(np.full(len(vids), 10.0))
                after = core.lane_states()
                v1 = np.array([after[v][2] if v in after else np.nan for v in vids])
                free = obs[:, 0] < TRUCK_MAX_MPS - 1.0
                rates += ((v1 - obs[:, 0]) / core.dt)[free & np.isfinite(v1)].tolist()
            assert len(rates) > 20
            top[name] = max(rates)
        finally:
            core.close()
    assert top["capped"] <= TRUCK_ACCEL + TOL_MPS2 and top["uncapped"] > 2.0, top

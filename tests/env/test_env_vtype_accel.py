"""Stage II holds a hidden vehicle to its vType's accel, as a deployment does
(``road.vtype.command_speeds``, ``deploy.safety.speed_commands``): SUMO applies a speed
command beyond it under the envs' speed modes, where its own Krauss never accelerates
harder. Real SUMO: trucks of accel 1.0 on a road whose policy bound is 2.6 m/s^2, driven at
full throttle in the snapshot env (``SectionCore``) and in demand episodes (``DemandCore``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import line_net
from section_files import routes_file, section_scenario
from test_section_env import true_completion

from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.rollout import rollout
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank, typical_vclass, typical_vtype
from macromicro_sumo.road.vtype import accel_limit, command_speeds
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

TRUCK_ACCEL, TRUCK_MAX_MPS, BOUND = 1.0, 25.0, 2.6
HORIZON = 8
TOL_MPS2 = 1e-6  # SUMO's speeds are doubles: the command applies to rounding


@pytest.fixture(scope="module")
def trucks(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth, net): trucks (accel 1.0, maxSpeed 25) every 4 s onto a
    1.6 km lane (limit 30 m/s) at 2 m/s, half instrumented; one run of 30 + 60 s."""
    folder = tmp_path_factory.mktemp("env_vtype_accel")
    net = line_net(folder, (600.0, 1600.0), 1, 30.0)
    routes = routes_file(
        folder / "trucks.rou.xml",
        [
            f'<vType id="truck" vClass="truck" length="12" minGap="2.5" accel="{TRUCK_ACCEL}" '
            f'decel="4.0" sigma="0" maxSpeed="{TRUCK_MAX_MPS}" speedFactor="1.0" speedDev="0"/>'
        ],
        ['<flow id="f" type="truck" begin="0" end="90" period="4" departSpeed="2">'
         '<route edges="A B"/></flow>'],
    )  # fmt: skip
    path = section_scenario(
        folder / "trucks.toml",
        net,
        routes,
        ["A", "B"],
        seed=3,
        penetration=0.5,
        simulation={"warmup_s": 30.0, "duration_s": 60.0, "n_runs": 1},
        detectors={"interval_s": 30.0},
        bounds={"accel_mps2": [-4.5, BOUND]},
        policy={"observation": "lookahead", "demand_horizon_s": 20.0},
    )
    sc = load_scenario(path)
    truth = load_section_truth(simulate_section(sc, folder / "gt", progress=False), sc)
    return sc, truth, net


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


def test_snapshot_env_holds_hidden_trucks_to_their_accel(trucks) -> None:
    sc, truth, net = trucks
    assert typical_vtype(truth) == "truck"  # the generated vehicles' vType
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_completion, HORIZON, 0)
    assert bank.accel_mps2 is not None and (bank.accel_mps2[bank.valid] == TRUCK_ACCEL).all()
    full = lambda core, obs, rng: np.full(int(core.hidden.sum()), 10.0)  # noqa: E731
    top = {}
    for name, b in (("capped", bank), ("uncapped", dataclasses.replace(bank, accel_mps2=None))):
        for safety in ("none", "sumo"):
            core = SectionCore(
                sc, truth.section, b, net, seed=0, vclass=typical_vclass(truth), safety=safety
            )
            try:
                ro = rollout(core, full, HORIZON, 0)
            finally:
                core.close()
            hidden = np.broadcast_to(bank.hidden[:, None, :], ro.accel_mps2.shape)
            # Below maxSpeed, where the throttle is what limits.
            free = hidden & (ro.speed_mps < TRUCK_MAX_MPS - 1.0)
            assert np.isfinite(ro.accel_mps2[free]).sum() > 50
            top[name, safety] = float(np.nanmax(np.where(free, ro.accel_mps2, np.nan)))
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

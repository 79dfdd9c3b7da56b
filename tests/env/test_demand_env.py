"""Demand episodes (``env.demand``) on a small section with inflow, an on-ramp merge and a
lane drop: vehicles enter during the episode and are driven as they do, and what the policy
observes there is what the section env and a deployment observe of the same SUMO state."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import merge_scenario  # noqa: E402

from macromicro_sumo.deploy.drivers import SectionSpeedDriver  # noqa: E402
from macromicro_sumo.deploy.drivers import section_observations as deploy_observations  # noqa: E402
from macromicro_sumo.deploy.population import DriveStats  # noqa: E402
from macromicro_sumo.deploy.safety import speed_commands  # noqa: E402
from macromicro_sumo.env.demand import DemandCore  # noqa: E402
from macromicro_sumo.env.driver_speed import (  # noqa: E402
    QUANTILE_LEVELS,
    DriverSpeeds,
    driver_entry,
    driver_levels,
    factors_at,
    sight_factors,
)
from macromicro_sumo.env.section_observations import section_observations  # noqa: E402
from macromicro_sumo.road.physics import idm_accel, observes_gap  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.sumo.simulation import Simulation  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402


def act(obs: np.ndarray) -> np.ndarray:
    """IDM on the observation (the merge's cars: 5 m long, limit 30 m/s), no network."""
    return idm_accel(obs[:, 0], obs[:, 2] - 5.0, obs[:, 3], 30.0, 1.2, 2.0, 3.0, 2.5)


@pytest.fixture(scope="module")
def merge(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth) of the merge: 2 runs of 60 s warm-up + 120 s."""
    folder = tmp_path_factory.mktemp("demand_merge")
    path = merge_scenario(
        folder,
        {"warmup_s": 60.0, "duration_s": 120.0, "n_runs": 2},
        policy={"observation": "lookahead", "demand_horizon_s": 30.0},
    )
    sc = load_scenario(path)
    gt = simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(gt, sc)


def test_vehicles_enter_and_an_idm_like_policy_drives_them_without_collisions(merge) -> None:
    sc, truth = merge
    core = DemandCore(sc, truth, truth.runs, 60)
    try:
        windows = core.windows(np.random.default_rng(0), 3)
        assert all(60.0 <= t0 <= 60.0 + 120.0 - 30.0 for _, t0 in windows)
        core.reset(*windows[0])
        seen: set[str] = set()
        first: list[str] = []
        rewards = []
        for t in range(60):
            vids, obs = core.observe()
            if t == 0:
                first = vids
            assert obs.shape == (len(vids), 6)
            seen.update(vids)
            res = core.step(act(obs))
            assert not res.collided and res.collisions == 0
            rewards.append(res.r_macro)
        assert first and len(seen - set(first)) >= 5  # vehicles entered during the episode
        assert min(rewards) > 0.0 and max(rewards) <= 1.0
        assert core.counts["vehicle_steps"] > 60 * len(first) * 0.5
    finally:
        core.close()


def test_observations_agree_with_the_section_env_and_the_deployment(merge) -> None:
    """One SUMO state, three observations: the demand core's, the section env's from arc
    positions (leaders along lane connections), the deployment driver's."""
    sc, truth = merge
    core = DemandCore(sc, truth, truth.runs, 60)
    sec = truth.section
    n_checked = 0
    try:
        core.reset(int(truth.runs[0]), 90.0)
        for t in range(40):
            vids, obs = core.observe()
            if t % 8 == 7 and vids:
                states = core.lane_states()
                # The env's observation from every vehicle on the section's arcs.
                on = [v for v in states if states[v][0] in sec.lanes]
                lane = np.array([sec.lanes[states[v][0]][1] for v in on])
                arc = np.array([sec.lanes[states[v][0]][2] + states[v][1] for v in on])
                speed = np.array([states[v][2] for v in on])
                env_obs, _, _ = section_observations(
                    sec, lane, arc, speed, np.ones(len(on), bool), sc.policy.observation
                )
                env_of = dict(zip(on, env_obs, strict=True))
                ref = np.stack([env_of[v] for v in vids])
                np.testing.assert_allclose(obs[:, [0, 1, 4, 5]], ref[:, [0, 1, 4, 5]], atol=1e-6)
                # Spacing and delta_v: the same leader, front to front (inside a junction
                # SUMO's lane geometry is not the section's straight arc: a metre).
                close = np.abs(obs[:, 2] - ref[:, 2]) < 1.0
                assert close.mean() >= 0.9, (obs[~close, 2], ref[~close, 2])
                np.testing.assert_allclose(obs[close, 3], ref[close, 3], atol=1e-6)
                # The deployment's driver on the same state: the same features.
                drv = SectionSpeedDriver(sc, sec, int(truth.runs[0]), act, "none")
                drv.types = dict(core.types)
                drv.vtypes = dict(core.vtypes)
                drv.shape_of = {v: core.vtypes[t].shape for v, t in core.types.items()}
                drv.has_lights = False
                dep, _, _ = deploy_observations(drv, core.sim, vids, states)
                np.testing.assert_allclose(obs, dep, atol=1e-9)
                n_checked += len(vids)
            core.step(act(obs))
    finally:
        core.close()
    assert n_checked > 50


def _deploy_driver(sc, core: DemandCore, run: int, speeds: DriverSpeeds | None):
    """A deployment's section driver on the core's SUMO state (``speeds``: its drivers'
    factors, ``policy.driver_speed``)."""
    drv = SectionSpeedDriver(sc, core.section, run, act, "none")
    drv.types = dict(core.types)
    drv.vtypes = dict(core.vtypes)
    drv.shape_of = {v: core.vtypes[t].shape for v, t in core.types.items()}
    drv.has_lights = False
    drv.driver_speeds = speeds
    return drv


def _entries(sc, truth, run: int, t0_s: float, speeds: DriverSpeeds) -> dict[str, float]:
    """SUMO's own drive of ``run`` until ``t0_s``: ``speeds`` asked of each population
    vehicle at its first step on the section, with the deployment's observation of it
    there (a deployment's "memory" driver sets its factor then); its speed ratio then
    (``sight_factors`` of that observation, a held or queued one drawn) per vehicle."""
    core = DemandCore(sc, truth, truth.runs, 60)
    at_entry: dict[str, float] = {}
    try:
        core.reset(run, sc.simulation.step_length_s)
        for k in range(int(round(t0_s / sc.simulation.step_length_s))):
            if k:
                core.sim.step()
                core._arrive(core.sim.departed())
            states = core.lane_states()
            new = sorted(
                v
                for v in core.population
                if v in states and states[v][0] in core.section.lanes and v not in at_entry
            )
            if new:
                drv = _deploy_driver(sc, core, run, speeds)
                plain, _, _ = deploy_observations(
                    _deploy_driver(sc, core, run, None), core.sim, new, states
                )
                deploy_observations(drv, core.sim, new, states)  # sets their factors
                ratio = _sight(sc, run, speeds.quantiles, new, plain)
                at_entry.update(zip(new, ratio.tolist(), strict=True))
    finally:
        core.close()
    return at_entry


def _sight(sc, run: int, q: np.ndarray, vids: list[str], plain: np.ndarray) -> np.ndarray:
    """ "memory"'s factors of ``vids`` first seen with observations ``plain``."""
    levels = driver_levels(sc.seed, run, vids)
    entry = driver_entry(sc)
    return sight_factors(q, plain, levels, entry, observes_gap(sc.policy.observation))


@pytest.mark.parametrize("kind", ["drawn", "memory"])
def test_drivers_take_the_desired_speed_factors_a_deployment_gives_them(merge, kind) -> None:
    """``policy.driver_speed``: a demand episode's driver observes the limits times the
    factor a deployment's ``DriverSpeeds`` gives the same vehicle of the same run ("drawn":
    a hash of (seed, run, vehicle); "memory": its speed ratio where it entered the section,
    for a vehicle already there when the window starts its entry before it, while SUMO
    drove it), kept while it is driven; every other feature as without factors."""
    sc0, truth = merge
    # the entry rule as set ("auto" is resolved by the stage that loads the truth, stop 47)
    sc = replace(sc0, policy=replace(sc0.policy, driver_speed=kind, driver_entry="queued"))
    q = np.linspace(0.8, 1.25, len(QUANTILE_LEVELS))  # ratios around a median of 1.025
    run, t0 = int(truth.runs[0]), 90.0
    deployed = DriverSpeeds(q, sc, run)  # the deployment's, asked where a vehicle enters
    at_entry = _entries(sc, truth, run, t0, deployed) if kind == "memory" else {}
    core = DemandCore(sc, truth, truth.runs, 60)
    factors: list[float] = []
    moved = 0  # window-start vehicles whose ratio at t0 is not their entry's
    try:
        core.set_driver_speeds(q)
        core.reset(run, t0)
        for t in range(30):
            vids, obs = core.observe()
            if vids:
                states = core.lane_states()
                dep, _, _ = deploy_observations(
                    _deploy_driver(sc, core, run, deployed), core.sim, vids, states
                )
                np.testing.assert_allclose(obs, dep, atol=1e-12)
                plain, _, _ = deploy_observations(
                    _deploy_driver(sc, core, run, None), core.sim, vids, states
                )
                if kind == "drawn":
                    f = factors_at(q, driver_levels(sc.seed, run, vids))
                else:  # the ratio where it entered, kept
                    now = _sight(sc, run, q, vids, plain)
                    for i, v in enumerate(vids):
                        at_entry.setdefault(v, float(now[i]))
                    f = np.array([at_entry[v] for v in vids])
                    if t == 0:
                        moved = int(np.count_nonzero(np.abs(now - f) > 0.02))
                np.testing.assert_allclose(
                    obs[:, [1, 4]], plain[:, [1, 4]] * f[:, None], rtol=1e-12
                )
                np.testing.assert_array_equal(obs[:, [0, 2, 3, 5]], plain[:, [0, 2, 3, 5]])
                factors += f.tolist()
            core.step(act(obs))
    finally:
        core.close()
    assert len(factors) > 100 and np.ptp(factors) > 0.1  # drivers of their own speeds
    assert kind == "drawn" or moved >= 3  # their factor at t0 would have been another


def test_driven_vehicles_are_held_to_their_vtypes_max_speed(merge) -> None:
    """Speed mode 32 applies a command above the vType's maxSpeed; the core holds every
    command to it: read from SUMO (the merge's cars: a passenger car's default), and with
    the cap the core keeps per vType (``vtypes``) lowered below the IDM policy's 30 m/s."""
    sc, truth = merge
    top = {}
    for cap in (None, 20.0):
        core = DemandCore(sc, truth, truth.runs, 60)
        try:
            core.reset(int(truth.runs[0]), 90.0)
            # SUMO's, above the limit
            assert core.vtypes and min(p.max_speed_mps for p in core.vtypes.values()) > 30.0
            if cap is not None:
                core.vtypes = {k: replace(p, max_speed_mps=cap) for k, p in core.vtypes.items()}
                core.reset(int(truth.runs[0]), 90.0)
            assert set(core.types) >= core.population  # each driven vehicle's vType known
            fastest = 0.0
            for _ in range(40):
                vids, obs = core.observe()
                core.step(act(obs))
                states = core.lane_states()
                fastest = max([fastest] + [states[v][2] for v in vids if v in states])
            top[cap] = fastest
        finally:
            core.close()
    assert top[20.0] <= 20.0 + 1e-9 and top[None] > 22.0, top


def test_a_demand_step_commands_what_the_deployment_without_its_layer_commands(merge) -> None:
    """One state, one policy: the speeds SUMO drives after a demand step are the commands
    the deployment's rule (``deploy.safety.speed_commands``, ``safety = "none"``, each
    vehicle held to its vType's maxSpeed and accel) gives the deployment's observation of
    that state; speed mode 32 applies them exactly. The deployment's default layer
    (``"sumo"``) is what the demand episodes leave out."""
    sc, truth = merge
    run = int(truth.runs[0])
    core = DemandCore(sc, truth, truth.runs, 60)
    checked = 0
    try:
        core.reset(run, 90.0)
        for _ in range(20):
            vids, obs = core.observe()
            states = core.lane_states()
            drv = _deploy_driver(sc, core, run, None)
            dep, _, _ = deploy_observations(drv, core.sim, vids, states)
            phys = [core.vtypes[core.types[v]] for v in vids]
            cmd = speed_commands(
                sc,
                act,
                "none",
                DriveStats(),
                dep,
                lambda: None,  # no layer asked
                vmax=np.array([p.max_speed_mps for p in phys]),
                accel=np.array([p.accel_mps2 for p in phys]),
            )
            res = core.step(act(obs))
            after = core.lane_states()
            kept = [i for i, v in enumerate(vids) if v in after and v not in res.collided]
            got = np.array([after[vids[i]][2] for i in kept])
            np.testing.assert_allclose(got, cmd[kept], atol=1e-9)
            checked += len(kept)
    finally:
        core.close()
    assert checked > 100


@pytest.mark.parametrize("entry", ["queued", "held"])
def test_memory_asks_sumo_what_is_ahead_of_an_entry_only_where_its_rule_reads_it(
    merge, entry, monkeypatch
) -> None:
    """``policy.driver_entry`` "queued" reads a first sight's speed and limit alone
    (``sight_factors``): the window's warm-up, where each entering driver's factor is set
    (``_remember_entries``), asks SUMO for no leaders or lane ends; "held" reads the leader
    (``held_at_sight``) and asks. Each entering driver has its factor either way."""
    sc0, truth = merge
    policy = replace(sc0.policy, driver_speed="memory", driver_entry=entry)
    sc = replace(sc0, policy=policy)
    asked = {"read_leaders": 0, "lane_end_m": 0}
    for name in asked:
        real = getattr(Simulation, name)

        def spy(self, *a, _real=real, _name=name, **k):
            asked[_name] += 1
            return _real(self, *a, **k)

        monkeypatch.setattr(Simulation, name, spy)
    core = DemandCore(sc, truth, truth.runs, 60)
    try:
        core.set_driver_speeds(np.linspace(0.8, 1.25, len(QUANTILE_LEVELS)))
        core.reset(int(truth.runs[0]), 90.0)
        on = [v for v, s in core.lane_states().items() if s[0] in core.section.lanes]
        entered = [v for v in on if v in core.population]
        assert len(entered) > 5 and set(entered) <= set(core.drivers.factor)
    finally:
        core.close()
    if entry == "queued":
        assert asked == {"read_leaders": 0, "lane_end_m": 0}
    else:
        assert asked["read_leaders"] > 10 and asked["lane_end_m"] > 10

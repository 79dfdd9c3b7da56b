"""The deployment's safety layer against adversarial commands (``deploy.safety``) and
the vType switch (``deploy.type_driver.SectionTypeDriver``): whatever a driver asks for, full
throttle, random accelerations from a seeded generator, hard braking, SUMO reports no
collision and nobody stands for good. Real SUMO."""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT, dump_toml, line_net, scenario_table
from deploy_nets import CAR, sparse_merge
from section_files import routes_file, section_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.population import SwitchedType, population_scenario
from macromicro_sumo.deploy.run import Drive, load_context, run_method, vtype_xml
from macromicro_sumo.deploy.safety import behind_commands, leader_safe_speed, safety_cap
from macromicro_sumo.deploy.type_driver import SectionTypeDriver
from macromicro_sumo.road.physics import safe_speed
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import load_section, record_run, run_section, simulate_section
from macromicro_sumo.truth.section_detectors import place_detectors

Act = Callable[[np.ndarray], np.ndarray]


def adversary(kind: str, a_min: float, a_max: float, seed: int) -> Act:
    """Commands that test the cap: full throttle; random accelerations in the bounds; or
    full throttle but for one vehicle (the first driven) that brakes at a_min, harder than
    any vehicle's decel, for 5 s in every 15, so that followers close up behind it first."""
    rng = np.random.default_rng(seed)
    if kind == "full":
        return lambda obs: np.full(len(obs), a_max)
    if kind == "random":
        return lambda obs: rng.uniform(a_min, a_max, len(obs))
    steps = iter(range(10**9))

    def brake(obs: np.ndarray) -> np.ndarray:
        # Up to the speed limit (obs[:, 1]) at a_max: followers close up at a moderate speed.
        a = np.minimum(a_max, (obs[:, 1] - obs[:, 0]) / 0.5)
        if next(steps) % 30 >= 20:
            a[0] = a_min
        return a

    return brake


@pytest.mark.parametrize("brake", ["own", "matched"])
@pytest.mark.parametrize(("kind", "a_min"), [("full", -6.0), ("random", -6.0), ("brake", -30.0)])
def test_no_command_makes_the_ring_collide(
    tmp_path: Path, kind: str, a_min: float, brake: str
) -> None:
    """The paper's ring with 9 vehicles of unequal decels (1.2 to 1.8 m/s^2) packed at
    35 m: a follower that brakes harder than its leader may not close in at no gap (it
    did: ``road.physics.safe_speed``); behind a leader that stops within one step (30
    m/s^2) its followers brake with it, not one step later (its command is known,
    ``deploy.drivers.behind_commands``). With either ``deploy.safety_brake``: "matched"
    plans a softer-braking follower's stop at its leader's decel."""
    table = scenario_table(
        {
            "fleet.n_vehicles": 9,
            "initial.min_spacing_m": 35.0,
            "bounds.accel_mps2": [a_min, 3.0],
            # Vehicles that can accelerate at the bound: commands are held to the vType's
            # accel (deploy.safety.speed_commands), which at the paper's 0.8-1.2 m/s^2
            # leaves the random adversary too weak to test the layer.
            "fleet.accel_mps2": [3.0, 3.0],
            "bounds.spacing_m": [40.0, 140.0],
            "simulation.duration_s": 90.0,
            "simulation.n_runs": 2,
            "deploy.safety_brake": brake,
        }
    )
    path = tmp_path / "ring.toml"
    path.write_text(dump_toml(table))
    # The ring as the closed one-lane section it loads as; every vehicle driven.
    sc = population_scenario(load_scenario(path))
    inputs, section, _ = load_section(sc)
    placed = place_detectors(sc, inputs, section)
    drivers: list[SectionSpeedDriver] = []

    def driver_for(run: int) -> SectionSpeedDriver:
        act = adversary(kind, *sc.bounds.accel_mps2, seed=run)
        drv = SectionSpeedDriver(sc, section, run, act, "sumo")
        drivers.append(drv)
        return drv

    trajs, rows, _ = run_section(
        sc, inputs, section, placed, tmp_path / "out", [0, 1], False, driver_for
    )
    assert [r["collisions"] for r in rows] == [0, 0], rows
    # The cap acted (the commands were dangerous) and the vehicles kept moving.
    assert sum(d.stats.safety_acted for d in drivers) > 10, [d.stats for d in drivers]
    length = section.length_m
    for traj in trajs:
        if kind != "random":  # capped, not stopped
            assert traj["speed_mps"].mean() > 5.0
        # Bumper gaps round the loop at every step: none below 0.
        for _, step in traj.groupby("time_s"):
            arc = np.sort(step["arc_m"].to_numpy())
            gaps = np.diff(np.append(arc, arc[0] + length)) - sc.fleet.length_m
            assert gaps.min() >= 0.0


def test_followers_brake_with_a_driven_leader_that_stops_within_a_step() -> None:
    """A platoon 0 <- 1 <- 2 (each follows the one before): 1 m/s slower than its leader
    each, 1 m apart (safe while the leader brakes at its decel), and the first stops
    within one step (a command of 0 m/s). ``safe_speed`` behind the leaders' present
    speeds would let vehicle 1 drive 5 m into it during the step; behind their commands
    every gap after the step is >= 0, and the chain reaches vehicle 2."""
    dt, b = 0.5, np.full(3, 4.5)
    speed = np.array([15.0, 14.0, 13.0])
    gap = np.array([500.0, 1.0, 1.0])  # bumper gap to the leader (minGap taken off)
    lead = np.array([-1, 0, 1])
    lead_speed = np.array([0.0, 15.0, 14.0])
    cmd = np.minimum(speed + 1.0, safe_speed(gap, lead_speed, b, b, dt))
    cmd[0] = 0.0
    assert cmd[1] > 10.0  # the leaders' present speeds leave room
    out = behind_commands(cmd, gap, lead, b, b, dt)
    after = gap[1:] + (out[:-1] - out[1:]) * dt
    assert np.all(after >= -1e-9), after
    assert out[0] == 0.0 and out[2] < cmd[2]  # the chain went on to vehicle 2
    # Where the leaders brake no harder than assumed, nothing changes.
    calm = np.minimum(speed, safe_speed(gap, lead_speed, b, b, dt))
    np.testing.assert_array_equal(behind_commands(calm, gap, lead, b, b, dt), calm)


def test_the_layer_caps_at_the_shared_leader_table() -> None:
    """``leader_safe_speed`` (the one safe speed a step, which a driver's merge yield reads
    too) is ``safe_speed`` behind an observed leader and no cap without one; the layer
    given it commands what it commands computing it itself, and never above it."""
    dt = 0.5
    rng = np.random.default_rng(3)
    n = 200
    v = rng.uniform(0.0, 30.0, n)
    obs = np.column_stack([v, np.full(n, 30.0), rng.uniform(5.0, 300.0, n), rng.normal(0, 3, n)])
    gap = np.where(rng.random(n) < 0.2, 250.0, rng.uniform(0.0, 120.0, n))
    b, b_l = rng.uniform(3.0, 6.0, n), rng.uniform(3.0, 9.0, n)
    lead = np.where(rng.random(n) < 0.5, rng.integers(0, n, n), -1)
    safe = leader_safe_speed(obs, gap, b, b_l, dt)
    has = gap < NO_LEADER_GAP_M
    assert np.isinf(safe[~has]).all() and np.isfinite(safe[has]).all()
    np.testing.assert_array_equal(safe[has], safe_speed(gap, v - obs[:, 3], b, b_l, dt)[has])
    cmd = v + rng.uniform(-4.5, 2.6, n) * dt
    own = safety_cap(cmd, obs, gap, b, b_l, lead, dt, 2.6, 0.2)
    shared = safety_cap(cmd, obs, gap, b, b_l, lead, dt, 2.6, 0.2, safe)
    np.testing.assert_array_equal(own[0], shared[0])
    assert own[1:] == shared[1:] and own[1] > 0
    assert np.all(shared[0] <= safe + 1e-12)


def test_behind_commands_skips_only_where_nothing_can_change() -> None:
    """Given the leader speeds the safe speed assumed, ``behind_commands`` skips its loop
    where no driven leader brakes harder than assumed: bit for bit the commands of the
    full loop, over seeded random platoons with leaders commanded exactly at the assumed
    braking, standing, slower than one step's braking, and at random."""
    rng = np.random.default_rng(11)
    dt, skipped, lowered = 0.5, 0, 0
    for _ in range(2000):
        n = int(rng.integers(2, 40))
        v = rng.uniform(0.0, 40.0, n) if rng.random() < 0.7 else rng.uniform(0.0, 3.0, n)
        b = rng.choice([3.0, 4.5, 4.65, 9.0], n)
        lead = np.where(rng.random(n) < 0.7, rng.integers(0, n, n), -1)
        lead[lead == np.arange(n)] = -1
        b_l = np.where(lead >= 0, b[np.maximum(lead, 0)], 9.0)
        v_l = np.where(lead >= 0, v[np.maximum(lead, 0)], 0.0)
        obs = np.column_stack([v, np.full(n, 44.4), np.full(n, 50.0), v - v_l])
        gap = np.where(lead >= 0, rng.uniform(-1.0, 60.0, n), NO_LEADER_GAP_M)
        safe = leader_safe_speed(obs, gap, b, b_l, dt)
        a = rng.choice([-9.0, -4.65, -4.5, 0.0, 2.6], n)
        a = a if rng.random() < 0.5 else rng.uniform(-6.0, 2.6, n)
        cmd = np.minimum(np.maximum(0.0, v + a * dt), safe)  # at most the safe speed
        if rng.random() < 0.3:  # leaders exactly at the braking safe_speed assumed
            for i in np.flatnonzero(lead >= 0):
                braked = max(0.0, obs[i, 0] - obs[i, 3] - max(b[i], b_l[i]) * dt)
                cmd[lead[i]] = min(cmd[lead[i]], braked)
        full = behind_commands(cmd, gap, lead, b, b_l, dt)
        short = behind_commands(cmd, gap, lead, b, b_l, dt, obs[:, 0] - obs[:, 3])
        np.testing.assert_array_equal(short, full)
        skipped += short is cmd
        lowered += bool((full < cmd).any())
    assert skipped > 100 and lowered > 500, (skipped, lowered)


def _spreewaldring(folder: Path) -> Path:
    """Spreewaldring (one lane, 31 race cars of minGap 0 queued 0.1 m apart at a standing
    start, kept looping), 40 s after 10 s of warm-up, its ground truth simulated."""
    table = tomllib.loads((ROOT / "scenarios" / "spreewaldring.toml").read_text())
    table["network"]["sumocfg"] = str(
        ROOT / "sumo_nets" / "spreewaldring" / "spreewaldring.sumocfg"
    )
    table["simulation"].update(warmup_s=10.0, duration_s=40.0, n_runs=2)
    table["detectors"]["interval_s"] = 20.0
    table["deploy"] = {"fcd_s": 20.0}
    path = folder / "spreewald.toml"
    path.write_text(dump_toml(table))
    return path


@pytest.mark.parametrize("how", ["defaults", "idm"])
def test_a_vtype_switch_waits_until_the_new_min_gap_fits(tmp_path: Path, how: str) -> None:
    """Switched where they queue 0.1 m apart, the race cars' new minGap (SUMO's default
    2.5 m, or an IDM's 2 m) put every one of them in collision (SUMO counts a gap below
    the follower's minGap); switched once it fits, none is, and still most of their
    steps are driven."""
    sc = load_scenario(_spreewaldring(tmp_path))
    gt = simulate_section(sc, tmp_path / "gt", progress=False)
    assert (pd.read_csv(gt / "runs.csv")["collisions"] == 0).all()
    ctx = load_context(sc, gt)
    theta = {"accel": 2.0, "decel": 4.0, "tau": 1.0, "minGap": 2.0, "speedFactor": 1.0}
    drive = Drive(defaults=True) if how == "defaults" else Drive(theta=theta)
    res = run_method(ctx, drive, tmp_path / how)
    assert (res.runs["collisions"] == 0).all(), res.runs.to_dict("records")
    steps = (sc.simulation.warmup_s + sc.simulation.duration_s) / sc.simulation.step_length_s
    assert res.runs["vehicle_steps_driven"].min() > 0.4 * 0.8 * 31 * steps


def _run_section(sc, driver, additional: tuple[Path, ...] = ()) -> tuple[pd.DataFrame, dict]:
    sim = Simulation(
        SumoOptions(
            sc.resolve(sc.network.net_file),
            additional,
            sc.simulation.step_length_s,
            sc.seed,
            route_files=tuple(sc.resolve(r) for r in sc.network.route_files),
            user_demand=True,
        )
    )
    try:
        return record_run(sim, sc, driver.section, 0, driver)
    finally:
        sim.close()


@pytest.mark.parametrize(
    ("floor_on", "min_mean_mps", "min_floor_share"),
    [("all", 0.2 * 30.0 * 0.9, 0.5), ("standing", 0.3, 0.2)],
)
def test_a_policy_that_always_brakes_cannot_stop_the_merge(
    tmp_path: Path, floor_on: str, min_mean_mps: float, min_floor_share: float
) -> None:
    """A policy that brakes at a_min whatever it sees would stand every car on the free
    road for good (SUMO teleports a car after 300 s standing, and the stream behind it
    jams): the safety layer's floor (a fifth of the limit, below the safe speed) keeps
    them rolling; nobody stands longer than the queue at the lane end asks, none collides.
    With ``deploy.safety_floor_on = "standing"`` each car is raised only once below 1 m/s
    and braked again: the stream crawls, but the same holds."""
    sc = load_scenario(sparse_merge(tmp_path, deploy={"safety_floor_on": floor_on}))
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B", "C"], False)
    a_min = sc.bounds.accel_mps2[0]
    drv = SectionSpeedDriver(sc, section, 0, lambda obs: np.full(len(obs), a_min), "sumo")
    df, stats = _run_section(sc, drv)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    driven = df[~df["observed"]].sort_values(["vehicle_id", "time_s"])
    standing = driven["speed_mps"] < 0.1
    # Longest stretch of standing steps of any driven car.
    runs = standing.groupby([driven["vehicle_id"], (~standing).cumsum()]).sum()
    assert runs.max() * sc.simulation.step_length_s < 20.0, runs.max()
    assert driven["speed_mps"].mean() > min_mean_mps, driven["speed_mps"].describe()
    assert drv.stats.floor_acted > min_floor_share * drv.stats.vehicle_steps_driven


@pytest.mark.parametrize("kind", ["full", "random"])
def test_no_command_makes_the_merge_collide(tmp_path: Path, kind: str) -> None:
    """On the merge (an acceleration lane that ends, lane changes, an added lane where
    SUMO's leader is on another lane index): full throttle, or random accelerations in the
    scenario's bounds [-4.5, 2.6] m/s^2 from a seeded generator, for every driven car."""
    sc = load_scenario(sparse_merge(tmp_path))
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B", "C"], False)
    act = adversary(kind, *sc.bounds.accel_mps2, seed=3)
    drv = SectionSpeedDriver(sc, section, 0, act, "sumo")
    df, stats = _run_section(sc, drv)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    assert drv.stats.vehicle_steps_driven > 2000
    if kind == "full":  # the cap did the work, and the cars drove
        assert drv.stats.safety_acted > 100, drv.stats
        assert df.loc[~df["observed"], "speed_mps"].mean() > 15.0


def test_a_vtype_switch_hands_back_where_the_own_min_gap_fits(tmp_path: Path) -> None:
    """Section A (300 m at 30 m/s) of a road A -> B whose B (2 m/s) queues the stream
    back onto A: cars switched to an IDM of minGap 0.5 m close up to ~1.5 m in the queue;
    handed back to their own vType (minGap 2.5 m) at A's end there, SUMO counted each in
    collision. Handed back once their own minGap fits, none is."""
    folder = tmp_path / "net"
    folder.mkdir()
    net = line_net(folder, (300.0, 700.0), 1, (30.0, 2.0))
    routes = routes_file(
        folder / "line.rou.xml",
        [CAR],
        ["<flow id='f' type='car' route='r' begin='0' end='3600' vehsPerHour='1800' "
         "departSpeed='max'/>"],
        ["<route id='r' edges='A B'/>"],
    )  # fmt: skip
    path = section_scenario(
        tmp_path / "line.toml",
        net,
        routes,
        ["A"],
        seed=5,
        penetration=0.01,
        simulation={"warmup_s": 0.0, "duration_s": 150.0, "n_runs": 2},
        detectors={"interval_s": 30.0},
    )
    sc = load_scenario(path)
    theta = {"accel": 2.6, "decel": 4.5, "tau": 0.5, "minGap": 0.5, "speedFactor": 1.0}
    text, type_of = vtype_xml({"car": ("passenger", 5.0)}, Drive(theta=theta))
    extra = folder / "switch.add.xml"
    extra.write_text(text)
    drv = SectionTypeDriver(sc, read_section(net, ["A"], False), 0, SwitchedType(type_of, 1.0))
    df, stats = _run_section(sc, drv, (extra,))
    assert stats["collisions"] == 0, stats
    assert drv.stats.vehicle_steps_driven > 1000
    # The queue reached back onto A: the cars handed back there were close.
    assert (df["speed_mps"] < 2.5).mean() > 0.2

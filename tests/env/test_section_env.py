"""Stage II on a section: SectionCore on real SUMO networks (a motorway, the ring), PPO on it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ROOT, dump_toml, netconvert

from macromicro_sumo.data.section import PSI_FIELDS, section_snapshots
from macromicro_sumo.env.section import SectionCore, section_macro_reward, section_target
from macromicro_sumo.env.section_bank import SectionBank, build_section_bank, typical_length
from macromicro_sumo.env.section_envs import true_section_completion
from macromicro_sumo.evaluation.idm_fit import fit_policy_prior
from macromicro_sumo.evaluation.section import micro_pairs
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.road.physics import idm_accel
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

HIGHWAY = ROOT / ".venv/lib/python3.11/site-packages/sumo/tools/game/highway/highway.net.xml"
HIGHWAY_EDGES = ["145354574", "189597495"]
RING = ROOT / "sumo_nets" / "ring_r100_e4.net.xml"
DT = 0.5
PSI = dict(
    mean_speed_mps=30.0,
    mean_spacing_m=60.0,
    std_spacing_m=20.0,
    speed_min_mps=0.0,
    speed_max_mps=50.0,
    spacing_min_m=7.0,
    spacing_max_m=np.inf,  # no spacing bounds (generator.spacing_bounds = "none")
    spacing_low_m=7.0,
)


def section_scenario(tmp_path: Path, net: Path, edges: list[str], closed: bool, **policy):
    table = {
        "name": "section_env_test",
        "network": {"kind": "sumo", "net_file": str(net)},
        "section": {"edges": edges, "closed": closed},
        "simulation": {"step_length_s": DT},
        "policy": {"observation": "lookahead", **policy},
    }
    path = tmp_path / "section.toml"
    path.write_text(dump_toml(table))
    return load_scenario(path)


def synthetic_bank(lanes, arcs, speeds, hidden, replay_speed=None, horizon=5, psi=None):
    """One episode; observed vehicles keep their lane and follow ``replay_speed`` (H+1, N)
    by Euler steps (NaN: off the section from that step on)."""
    lanes, arcs, speeds = np.asarray(lanes), np.asarray(arcs, float), np.asarray(speeds, float)
    hidden = np.asarray(hidden, bool)
    n = len(arcs)
    if replay_speed is None:
        replay_speed = np.tile(speeds, (horizon + 1, 1))
    rv = np.array(replay_speed, float)
    rv[:, hidden] = np.nan
    ra = arcs + np.concatenate([np.zeros((1, n)), np.cumsum(rv[1:] * DT, axis=0)])
    rl = np.where(np.isnan(rv), np.nan, lanes.astype(float))
    psi = np.array([(psi or PSI)[f] for f in PSI_FIELDS])
    return SectionBank(
        lane0=lanes[None].astype(np.int64),
        arc0_m=arcs[None],
        speed0_mps=speeds[None],
        length_m=np.full((1, n), 5.0),
        valid=np.ones((1, n), bool),
        hidden=hidden[None],
        psi=psi[None],
        replay_lane=rl[None],
        replay_arc_m=ra[None],
        replay_speed_mps=rv[None],
        gt_accel_mps2=(np.diff(rv, axis=0) / DT)[None],
        true_lane=rl[None],
        true_arc_m=ra[None],
        true_speed_mps=rv[None],
        true_valid=np.isfinite(rv)[None],
        true_length_m=np.full((1, n), 5.0),
        run=np.array([0]),
        time_s=np.array([0.0]),
    )


@pytest.fixture(scope="module")
def highway():
    return read_section(HIGHWAY, HIGHWAY_EDGES, False)


def test_insertion_replay_and_commands_are_exact(tmp_path, highway):
    """Vehicles sit where asked; observed vehicles replay their speeds (and positions);
    hidden ones follow v' = max(0, v + a dt) with a clipped to the bounds."""
    sc = section_scenario(tmp_path, HIGHWAY, HIGHWAY_EDGES, False)
    lanes, arcs = [0, 1, 2, 0, 2], [100.0, 300.0, 600.0, 700.0, 250.0]
    speeds = [30.0, 35.0, 40.0, 25.0, 47.0]  # 47 m/s is above the 44.44 m/s limit
    hidden = [False, True, False, True, True]
    replay = np.array([[30.0, 35, 40, 25, 47]] * 6)
    replay[:, 0] += np.arange(6) * 0.5
    replay[:, 2] -= np.arange(6) * 1.0
    bank = synthetic_bank(lanes, arcs, speeds, hidden, replay)
    core = SectionCore(sc, highway, bank, HIGHWAY, seed=0, safety="none")  # exact commands
    try:
        core.reset(0)
        np.testing.assert_array_equal(core.lane, lanes)
        np.testing.assert_allclose(core.arc, arcs, atol=0.01)
        a_min, a_max = sc.bounds.accel_mps2
        for t in range(5):
            accel = np.array([1.0, -50.0, 50.0])  # the last two are clipped
            v0 = core.speed[bank.hidden[0]].copy()
            res = core.step(accel)
            assert not res.error and not res.truncated and res.active.all()
            want = np.maximum(0.0, v0 + np.clip(accel, a_min, a_max) * DT)
            np.testing.assert_allclose(core.speed[bank.hidden[0]], want, atol=1e-9)
            obs = ~bank.hidden[0]
            np.testing.assert_allclose(
                core.speed[obs], bank.replay_speed_mps[0, t + 1, obs], atol=1e-9
            )
            np.testing.assert_allclose(core.arc[obs], bank.replay_arc_m[0, t + 1, obs], atol=0.01)
    finally:
        core.close()


def test_vehicles_leave_the_open_end_and_their_records(tmp_path, highway):
    sc = section_scenario(tmp_path, HIGHWAY, HIGHWAY_EDGES, False)
    replay = np.array([[30.0, 30.0, 30.0]] * 6)
    replay[3:, 2] = np.nan  # the observed vehicle's record ends (it left in the ground truth)
    bank = synthetic_bank(
        [1, 1, 0], [200.0, 805.0, 400.0], [30.0, 30.0, 30.0], [True, True, False], replay
    )
    core = SectionCore(sc, highway, bank, HIGHWAY, seed=0)
    try:
        core.reset(0)
        active = []
        for _ in range(5):
            res = core.step(np.zeros(2))
            assert not res.error
            active.append(res.active.copy())
        active = np.array(active)
        assert active[:, 0].all()  # far from the end: stays
        assert not active[-1, 1] and active[0, 1]  # 805 m + 30 m/s: off the 822.6 m section
        np.testing.assert_array_equal(active[:, 2], [True, True, False, False, False])
        assert set(core.sim.vehicle_ids()) == {core.ids[0]}
    finally:
        core.close()


def test_observations_and_reward_match_direct_computation(tmp_path, highway):
    sc = section_scenario(tmp_path, HIGHWAY, HIGHWAY_EDGES, False)
    lanes, arcs = [0, 0, 0, 1, 1], [100.0, 160.0, 250.0, 130.0, 600.0]
    speeds = [30.0, 31.0, 29.0, 35.0, 40.0]
    hidden = [False, True, False, True, False]
    bank = synthetic_bank(lanes, arcs, speeds, hidden)
    core = SectionCore(sc, highway, bank, HIGHWAY, seed=0)
    try:
        o = core.reset(0)
        # spacing = the gap to the next vehicle in the same lane (front to front); one 470 m
        # ahead is beyond the look-ahead (NO_LEADER_GAP_M): none, as the deployment sees it,
        # while the reward below keeps its spacing
        np.testing.assert_allclose(
            o[:, 2], [60.0, 90.0, NO_LEADER_GAP_M, NO_LEADER_GAP_M, NO_LEADER_GAP_M], atol=0.01
        )
        np.testing.assert_allclose(o[:, 3], [-1.0, 2.0, 0.0, 0.0, 0.0])
        np.testing.assert_allclose(o[:, 1], 44.44)
        # lookahead: the next edge starts at 547.95 m; the last edge looks at the section end
        np.testing.assert_allclose(
            o[:, 5], [447.95, 387.95, 297.95, 417.95, highway.length_m - 600.0], atol=0.01
        )
        res = core.step(np.zeros(2))
        v, s = core.speed, core.arc
        gaps = np.array(
            [s[1] - s[0], s[2] - s[1], s[4] - s[3]]
        )  # pairs; only touching hidden count
        a = gaps[[0, 1, 2]]
        l_speed = (v.mean() / PSI["mean_speed_mps"] - 1) ** 2
        l_mean = (a.mean() / PSI["mean_spacing_m"] - 1) ** 2
        l_min = (np.maximum(0, PSI["spacing_min_m"] - a) ** 2).mean() / PSI["spacing_min_m"] ** 2
        # the measured dispersion (data.objective): variances around the measured mean
        d_mean, d_std = PSI["mean_spacing_m"], PSI["std_spacing_m"]
        l_var = abs(((a - d_mean) ** 2).mean() - d_std**2) / d_mean**2
        want = 1 / (
            1 + sc.generator.lambda_v * l_speed + sc.generator.lambda_d * (l_mean + l_min + l_var)
        )
        assert res.r_macro == pytest.approx(want, rel=1e-9)
        assert res.terms["L_speed"] == pytest.approx(l_speed, rel=1e-9)
    finally:
        core.close()


def two_cars_no_hidden(speed_mps: float) -> tuple:
    """section_macro_reward's arguments: two observed cars in one lane, psi with a NaN std."""
    return (
        np.array([speed_mps, speed_mps]),
        np.array([50.0, NO_LEADER_GAP_M]),
        np.array([1, -1]),
        np.array([False, False]),
        np.array([True, True]),
        section_target(np.array([30.0, 60.0, np.nan, 0.0, 50.0, 7.0])),
        0.5,
        0.5,
    )


def test_reward_with_no_hidden_pair_and_nan_std():
    r, terms = section_macro_reward(*two_cars_no_hidden(30.0))
    assert r == 1.0 and terms["L_var"] == 0.0


def test_reward_speed_scale_charges_a_bias_in_mps():
    """policy.macro_speed_scale_mps on a section: a bias of the scale costs L_speed = 1."""
    r_paper, paper = section_macro_reward(*two_cars_no_hidden(30.2))
    r_scaled, scaled = section_macro_reward(*two_cars_no_hidden(30.2), 0.2)
    assert paper["L_speed"] == pytest.approx((0.2 / 30.0) ** 2)
    assert scaled["L_speed"] == pytest.approx(1.0)
    assert r_scaled == pytest.approx(1 / 1.5) and r_paper > 0.9999


def test_closed_ring_gives_the_leaders_in_arc_order(tmp_path):
    """The ring as a one-lane closed section: every vehicle's leader is the next one round
    the loop and its spacing the arc to it, front to front (what the ring's own core gave
    until stop 25), at every step of driven and replayed vehicles."""
    n, h = 5, 6
    rng = np.random.default_rng(3)
    # Spread out: an observed vehicle replays its record only while that is safe.
    arcs = np.arange(n) * 125.0 + rng.uniform(0, 20, n)
    speeds = rng.uniform(10, 14, n)
    hidden = np.array([True, False, True, True, False])
    replay = speeds + rng.uniform(-0.3, 0.3, (h + 1, n))
    replay[0] = speeds
    accels = rng.uniform(-1.0, 0.5, (h, hidden.sum()))
    sc = section_scenario(tmp_path, RING, ["e0", "e1", "e2", "e3"], True)
    section = read_section(RING, ["e0", "e1", "e2", "e3"], True)
    length = section.length_m
    sbank = synthetic_bank(np.zeros(n, int), arcs, speeds, hidden, replay, horizon=h)
    core = SectionCore(sc, section, sbank, RING, seed=0)

    def check() -> None:
        order = np.argsort(core.arc)
        nxt = np.empty(n, dtype=np.int64)
        nxt[order] = np.roll(order, -1)
        np.testing.assert_array_equal(core.leader, nxt)
        np.testing.assert_allclose(
            core.spacing, np.mod(core.arc[nxt] - core.arc, length), atol=0.01
        )

    try:
        core.reset(0)
        check()
        for t in range(h):
            res = core.step(accels[t])
            assert not res.error and res.active.all()
            check()
    finally:
        core.close()


@pytest.fixture(scope="module")
def highway_truth(tmp_path_factory):
    """A short ground truth of the Bremen motorway section (the user's demand)."""
    folder = tmp_path_factory.mktemp("section_env")
    src = ROOT / "scenarios" / "highway_bremen.toml"
    text = src.read_text().replace('"../sumo_nets', f'"{ROOT}/sumo_nets')
    text = text.replace("duration_s = 600.0", "duration_s = 120.0").replace(
        "n_runs = 4", "n_runs = 2"
    )
    # Its 240 s comparison would be the whole shortened run: the detectors' own instead.
    text = text.replace("compare_interval_s = 240.0", "compare_interval_s = 0.0")
    path = folder / "highway.toml"
    path.write_text(text)
    sc = load_scenario(path)
    out = simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(out, sc)


def test_recorded_scene_is_replayed_and_ppo_trains(highway_truth, tmp_path):
    """On the real motorway ground truth: observed vehicles replay their records exactly
    while that is safe (lane changes and junctions included), no collision; PPO trains and the policy loads with its
    observation normalisation."""
    sc, truth = highway_truth
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_section_completion, 10, 0)
    assert bank.true_valid[:, 0].sum(axis=1).tolist() == bank.valid.sum(axis=1).tolist()
    net = ROOT / "sumo_nets" / "highway_bremen" / "highway.net.xml"
    core = SectionCore(sc, truth.section, bank, net, seed=0)
    try:
        for ep in range(0, len(bank), 3):
            core.reset(ep)
            for t in range(10):
                res = core.step(np.zeros(int(bank.hidden[ep].sum())))
                assert not res.error and not res.collision
                # exact while on record (hidden vehicles hold their speed here, so an
                # observed one may have to brake behind one: it then leaves its record)
                on = bank.observed[ep] & res.active & ~core.off_record
                np.testing.assert_allclose(
                    core.speed[on], bank.replay_speed_mps[ep, t + 1, on], atol=1e-6
                )
                np.testing.assert_allclose(
                    core.arc[on], bank.replay_arc_m[ep, t + 1, on], atol=0.01
                )
                assert (core.lane[on] == bank.replay_lane[ep, t + 1, on]).all()
    finally:
        core.close()
    torch.set_num_threads(1)
    sc = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, episodes_per_update=4))
    # The example's prior (policy.prior), fitted to the observed pairs as the stage does.
    obs, acc = micro_pairs(sc, truth, truth.runs)
    prior, _ = fit_policy_prior(
        sc.policy.prior, obs, acc, typical_length(truth), sc.simulation.step_length_s
    )
    res = train_policy(
        sc,
        bank,
        tmp_path,
        updates=2,
        progress=False,
        make_core=lambda b, seed: SectionCore(sc, truth.section, b, net, seed=seed),
        prior_params=prior,
    )
    assert len(res["log"]) == 2 and np.isfinite(res["log"][-1]["r_macro"])
    agent = load_policy(tmp_path / "policy.pt", sc)
    assert agent.prior == sc.policy.prior
    assert torch.equal(agent.shift, res["agent"].shift) and not torch.equal(
        agent.scale, torch.ones(6)
    )


def test_replayed_vehicle_never_drives_into_a_generated_one(tmp_path, highway):
    """A generated vehicle just ahead of an observed vehicle's recorded path, much slower:
    the observed vehicle keeps its record only while that is safe, then brakes (counted),
    and is never moved back onto its record into the other vehicle."""
    sc = section_scenario(tmp_path, HIGHWAY, HIGHWAY_EDGES, False)
    bank = synthetic_bank([0, 0], [100.0, 130.0], [30.0, 12.0], [False, True], horizon=8)
    core = SectionCore(sc, highway, bank, HIGHWAY, seed=0, safety="none")
    try:
        core.reset(0)
        for _ in range(8):
            res = core.step(np.zeros(1))  # the generated vehicle holds 12 m/s
            assert not res.collision and not res.error
            assert core.arc[1] - core.arc[0] > 5.0  # bumpers apart (5 m cars)
        assert core.off_record[0] and core.counts["replay_off_record"] == 1
        assert core.counts["replay_capped"] >= 1 and core.counts["replay_vehicles"] == 1
        assert core.speed[0] < 30.0
    finally:
        core.close()


def test_recorded_lane_change_into_a_generated_vehicle_waits(tmp_path, highway):
    """A recorded lane change onto a lane where a generated vehicle drives alongside is
    postponed (counted), not forced with moveTo into it."""
    sc = section_scenario(tmp_path, HIGHWAY, HIGHWAY_EDGES, False)
    bank = synthetic_bank([0, 1], [100.0, 102.0], [30.0, 30.0], [False, True], horizon=3)
    lane = bank.replay_lane.copy()
    lane[0, 1:, 0] = 1.0  # the record changes to lane 1 at once
    bank = dataclasses.replace(bank, replay_lane=lane)
    core = SectionCore(sc, highway, bank, HIGHWAY, seed=0, safety="none")
    try:
        core.reset(0)
        res = core.step(np.zeros(1))
        assert not res.collision and core.lane[0] == 0
        assert core.counts["replay_moves_refused"] >= 1 and core.off_record[0]
    finally:
        core.close()


def test_held_back_replayed_vehicle_catches_up_with_its_record(tmp_path, highway):
    """An observed vehicle held back by a slower generated vehicle returns onto its
    recorded position and speed once the way is free, never closer than safe on the way,
    and the steps it spent off its record and its lag are counted."""
    sc = section_scenario(tmp_path, HIGHWAY, HIGHWAY_EDGES, False)
    bank = synthetic_bank([0, 0], [100.0, 125.0], [30.0, 20.0], [False, True], horizon=30)
    core = SectionCore(sc, highway, bank, HIGHWAY, seed=0, safety="none")
    try:
        core.reset(0)
        held = False
        for _ in range(30):
            res = core.step(np.full(1, 2.6))  # the generated vehicle speeds up to 39 m/s
            assert not res.collision and not res.error
            assert core.arc[1] - core.arc[0] > 5.0
            held |= bool(core.off_record[0])
        assert held and core.counts["replay_returned"] == 1 and not core.off_record[0]
        assert core.counts["replay_off_steps"] >= 2 and core.counts["replay_lag_m"] > 1.0
        assert abs(core.arc[0] - bank.replay_arc_m[0, 30, 0]) <= 0.01
        assert core.speed[0] == pytest.approx(30.0, abs=1e-6)
    finally:
        core.close()


def signal_net(folder: Path, state: str) -> Path:
    """One lane A (300 m) -> a traffic light whose one phase is ``state`` for good -> B
    (200 m), built by netconvert (the program in the net: the env loads no additional)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "t.tll.xml").write_text(
        '<tlLogics>\n<tlLogic id="tl" type="static" programID="0" offset="0">\n'
        f'<phase duration="10000" state="{state}"/>\n</tlLogic>\n</tlLogics>\n'
    )
    return netconvert(
        folder,
        '<node id="n0" x="0" y="0"/>\n<node id="tl" x="300" y="0" type="traffic_light"/>\n'
        '<node id="n2" x="500" y="0"/>',
        '<edge id="A" from="n0" to="tl" numLanes="1" speed="15"/>\n'
        '<edge id="B" from="tl" to="n2" numLanes="1" speed="15"/>',
        extra=("--tllogic-files", str(folder / "t.tll.xml")),
    )


def idm_policy(obs: np.ndarray) -> np.ndarray:
    """IDM on the observation (v0 = the limit; one vehicle: its leader is a standing stop
    point, its spacing SUMO's gap to its stop + minGap 2.5 m + the own 5 m)."""
    v, limit, spacing, dv = obs[:, 0], obs[:, 1], obs[:, 2], obs[:, 3]
    gap = np.where(spacing < NO_LEADER_GAP_M, spacing - 7.5, 1e6)
    return idm_accel(v, np.maximum(gap - 1.0, 0.1), dv, limit, 1.2, 2.0, 3.0, 2.0)


@pytest.mark.parametrize("state", ["r", "y"])
def test_policy_stops_at_a_red_or_yellow_light(tmp_path, state):
    """A red (or yellow) signal ahead is a standing leader at the stop line in the
    observation: its spacing is SUMO's distance to the stop line less jmStoplineGap (1 m)
    plus minGap 2.5 m and the own 5 m length (``road.leaders.standing_spacing_m``), and an
    IDM policy driving by it (exact commands: SUMO does not brake for it) stops before the
    line."""
    net = signal_net(tmp_path / "net", state)
    sec = read_section(net, ["A", "B"], False)
    sc = section_scenario(tmp_path, net, ["A", "B"], False)
    bank = synthetic_bank([0], [100.0], [14.0], [True], horizon=80)
    core = SectionCore(sc, sec, bank, net, seed=0, safety="none")
    line = float(sec.offsets_m[0] + sec.lengths_m[0])
    try:
        obs = core.reset(0)
        assert obs[0, 2] == pytest.approx(core.sim.stop_line_m(core.ids[0]) + 6.5, abs=1e-6)
        assert obs[0, 2] == pytest.approx(line - 100.0 + 6.5, abs=1e-6)
        assert obs[0, 3] == pytest.approx(14.0)  # closing on a standing leader
        for _ in range(80):
            res = core.step(idm_policy(obs))
            obs = res.obs
            assert not res.collision and not res.error and res.active[0]
            assert core.arc[0] <= line  # never past the stop line
            want = max(line - core.arc[0] - 1.0, 0.0) + 7.5
            assert obs[0, 2] == pytest.approx(want, abs=1e-6)
        assert core.speed[0] < 0.1 and line - core.arc[0] < 5.0  # stopped at the line
    finally:
        core.close()


def test_green_light_is_no_leader(tmp_path):
    """A green signal is not a stop point: no leader, and the vehicle drives through."""
    net = signal_net(tmp_path / "net", "G")
    sec = read_section(net, ["A", "B"], False)
    sc = section_scenario(tmp_path, net, ["A", "B"], False)
    bank = synthetic_bank([0], [250.0], [14.0], [True], horizon=10)
    core = SectionCore(sc, sec, bank, net, seed=0, safety="none")
    try:
        obs = core.reset(0)
        assert obs[0, 2] == NO_LEADER_GAP_M and core.leader[0] == -1
        for _ in range(10):
            obs = core.step(idm_policy(obs)).obs
        assert core.arc[0] > sec.offsets_m[1]  # on B, past the light
    finally:
        core.close()

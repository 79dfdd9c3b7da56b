"""The batched env core: B scenes in one SUMO run of B network copies give each scene the
trajectory, observations and reward ``SectionCore`` gives it alone; its gymnasium VectorEnv."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import ROOT, SMALL_RING, write_scenario
from test_section_env import section_scenario, synthetic_bank

from macromicro_sumo.data.section import section_snapshots, split_runs
from macromicro_sumo.env.batched import BatchedSectionCore
from macromicro_sumo.env.batched_envs import SectionHiddenVectorEnv
from macromicro_sumo.env.batched_scene import batch_macro_reward, loop_observations
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import (
    build_section_bank,
    section_macro_reward,
    section_target,
)
from macromicro_sumo.env.section_envs import true_section_completion
from macromicro_sumo.env.section_observations import section_observations
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.sumo.tiling import copy_id, tile_net
from macromicro_sumo.truth.section import load_section_truth

RING = ROOT / "sumo_nets" / "ring_r100_e4.net.xml"
EDGES = ["e0", "e1", "e2", "e3"]


def test_tiled_copies_have_the_original_geometry(tmp_path):
    """Every copy of the ring reads as the same section (offsets, lengths, limits, links)."""
    out = tile_net(RING, 3, tmp_path / "tiled.net.xml")
    base = read_section(RING, EDGES, True)
    for b in range(3):
        sec = read_section(out, [copy_id(b, e) for e in EDGES], True)
        np.testing.assert_array_equal(sec.offsets_m, base.offsets_m)
        np.testing.assert_array_equal(sec.limits_mps, base.limits_mps)
        np.testing.assert_array_equal(sec.links, base.links)
        assert sec.length_m == base.length_m
    with pytest.raises(UserError, match="not a readable SUMO network"):
        tile_net(tmp_path / "missing.net.xml", 2, tmp_path / "x.net.xml")


def test_loop_observations_and_reward_match_the_single_scene_functions():
    """Without SUMO: random rows with gaps in the slots, equal positions and a lone
    vehicle give ``section_observations`` and ``section_macro_reward`` per row."""
    sec = read_section(RING, EDGES, True)
    rng = np.random.default_rng(4)
    b, n = 6, 5
    arc = rng.uniform(0, sec.length_m, (b, n))
    arc[1, 2] = arc[1, 3]  # equal positions: slot order, as the single-scene sort
    active = rng.random((b, n)) < 0.8
    active[2] = [False, False, True, False, False]  # a lone vehicle follows itself
    speed = rng.uniform(8, 14, (b, n))
    hidden = rng.random((b, n)) < 0.5
    limits = np.repeat(sec.limits_mps[None], b, axis=0) * rng.uniform(0.8, 1.0, (b, 1, 1))
    factor = rng.uniform(0.9, 1.0, (b, n))
    psi = np.tile(
        np.array([12.0, 125.0, 20.0, 10.0, 14.0, 100.0, np.inf, 100.0]), (b, 1)
    ) + rng.uniform(0, 1, (b, 8))
    obs, leader, spacing = loop_observations(sec, limits, arc, speed, active, 6, factor)
    r, terms = batch_macro_reward(speed, spacing, leader, hidden, active, psi, 0.5, 0.5, 0.1)
    for i in range(b):
        sec_i = dataclasses.replace(sec, limits_mps=limits[i])
        o, ld, sp = section_observations(
            sec_i, np.zeros(n, int), arc[i], speed[i], active[i], "lookahead", None, None, factor[i]
        )
        np.testing.assert_allclose(obs[i], o, atol=1e-12)
        np.testing.assert_array_equal(leader[i], ld)
        np.testing.assert_allclose(spacing[i], sp, atol=1e-12)
        r_i, _ = section_macro_reward(
            speed[i], sp, ld, hidden[i], active[i], section_target(psi[i]), 0.5, 0.5, 0.1
        )
        assert r[i] == pytest.approx(r_i, abs=1e-12)
    assert set(terms) >= {"L_speed", "L_mean", "L_var"}


@pytest.fixture(scope="module")
def ring_bank(small_ring_gt, tmp_path_factory):
    sc = load_scenario(write_scenario(tmp_path_factory.mktemp("batched"), SMALL_RING))
    truth = load_section_truth(small_ring_gt, sc)
    runs = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["train"]
    snaps = section_snapshots(truth, sc, runs, (1, 3))
    bank = build_section_bank(sc, truth, snaps, true_section_completion, sc.policy.horizon, 0)
    return sc, truth.section, bank, scenario_inputs(sc).net_file


def dense(bank, factor: float):
    """The bank's scenes squeezed to ``factor`` of their spread (records shifted alike):
    vehicles close enough that SUMO's safe speed caps commands, replay leaves its record;
    below 1, lengths of 4, 5 and 6 m that change per slot from one episode to the next."""
    if factor == 1.0:
        return bank
    arc0 = bank.arc0_m * factor
    shift = (arc0 - bank.arc0_m)[:, None, :]
    e, n = np.indices(bank.length_m.shape)
    return dataclasses.replace(
        bank,
        arc0_m=arc0,
        replay_arc_m=bank.replay_arc_m + shift,
        length_m=4.0 + (e + n) % 3,
    )


@pytest.mark.parametrize(
    "safety, squeeze, observation",
    [
        ("sumo", 1.0, None),
        ("none", 1.0, None),
        ("sumo", 0.15, None),
        ("none", 0.15, None),
        ("sumo", 0.15, "lookahead_gap"),
    ],
)
def test_a_scene_among_b_copies_drives_as_it_does_alone(ring_bank, safety, squeeze, observation):
    """Three scenes with staggered resets (scene 1 restarts mid-way while the others drive
    on; a reset places the scene's vehicles on the road where a fresh insertion would put
    them) give, scene by scene, SectionCore's observations, rewards, positions and speeds
    under the same actions, to the bit, and the same replay counters; squeezed scenes
    (``dense``) take the capped, off-record and catch-up paths. With the gap layout and
    squeezed scenes' 4-6 m vehicles: each leader's own length, as the single core's."""
    sc, section, bank, net = ring_bank
    if observation is not None:
        sc = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, observation=observation))
    bank = dense(bank, squeeze)
    h, b = bank.horizon, 3
    rng = np.random.default_rng(7)
    n_steps = 2 * h + 3
    accel = rng.uniform(-1.1, 0.5, (n_steps, b, bank.valid.shape[1]))
    starts = {0: [0, h + 1], 1: [0, 4, 4 + h + 1], 2: [0, h + 1]}  # call index of each reset
    episodes = {s: list(rng.integers(len(bank), size=len(v))) for s, v in starts.items()}
    core = BatchedSectionCore(sc, section, bank, net, b, seed=0, safety=safety)
    got: dict[tuple[int, int], list] = {}  # (scene, episode #) -> [(obs, r, arc, speed)]
    try:
        for c in range(n_steps):
            reset = np.full(b, -1)
            for s in range(b):
                if c in starts[s]:
                    reset[s] = episodes[s][starts[s].index(c)]
            res = core.step(accel[c], reset)
            assert not res.truncated.any(), res.errors
            for s in range(b):
                k = max(i for i, c0 in enumerate(starts[s]) if c0 <= c)
                if res.was_reset[s] or res.stepped[s]:
                    got.setdefault((s, k), []).append(
                        (res.obs[s], res.r_macro[s], core.arc[s].copy(), core.speed[s].copy())
                    )
        batched_counts = dict(core.counts)
    finally:
        core.close()
    single = SectionCore(sc, section, bank, net, seed=0, safety=safety)
    try:
        for (s, k), rows in got.items():
            c0 = starts[s][k]
            obs = single.reset(int(episodes[s][k]))
            np.testing.assert_array_equal(obs, rows[0][0])
            for t, (o, r, arc, speed) in enumerate(rows[1:]):
                res = single.step(accel[c0 + 1 + t, s][single.hidden])
                np.testing.assert_array_equal(res.obs, o)
                assert res.r_macro == r
                np.testing.assert_array_equal(single.arc, arc)
                np.testing.assert_array_equal(single.speed, speed)
        assert len(got) == 7 and len(got[0, 0]) == h + 1 and len(got[1, 0]) == 4
    finally:
        single.close()
    # The single core ran the episodes in another order; the sums agree.
    for key in ("replay_steps", "replay_capped", "hidden_steps", "safety_capped"):
        assert batched_counts[key] == single.counts[key], key
    assert (batched_counts["replay_capped"] > 0) == (squeeze < 1), batched_counts


def test_batched_core_refuses_sections_it_does_not_model(ring_bank):
    sc, section, bank, net = ring_bank
    with pytest.raises(UserError, match="closed one-lane sections"):
        BatchedSectionCore(sc, dataclasses.replace(section, closed=False), bank, net, 2)


def test_capped_replay_catches_up_the_same_way(tmp_path):
    """An observed vehicle close behind a braking hidden one is capped by SUMO's safe speed
    and catches up on its record afterwards: the off-record path gives, in a batch of two
    scenes (one braking, one not), what SectionCore gives each alone."""
    h = 10
    sc = section_scenario(tmp_path, RING, EDGES, True)
    section = read_section(RING, EDGES, True)
    bank = synthetic_bank(
        [0, 0, 0, 0], [100.0, 88.0, 300.0, 450.0], [12.0] * 4, [True, False, True, False],
        horizon=h,
    )  # fmt: skip
    brake = np.where(np.arange(h) < 5, -1.1, 0.5)[:, None]
    accel = np.zeros((h, 2, 4))
    accel[:, 0, [0, 2]] = brake  # scene 0: the leader of the observed vehicle brakes
    accel[:, 1, [0, 2]] = 0.3
    core = BatchedSectionCore(sc, section, bank, RING, 2, seed=0)
    try:
        core.reset(np.zeros(2, dtype=np.int64))
        rows = [[core.step(accel[t]), core.arc.copy(), core.speed.copy()] for t in range(h)]
        counts = dict(core.counts)
    finally:
        core.close()
    assert counts["replay_capped"] > 0 and counts["replay_returned"] > 0
    for s in range(2):
        single = SectionCore(sc, section, bank, RING, seed=0)
        try:
            single.reset(0)
            for t, (res_b, arc, speed) in enumerate(rows):
                res = single.step(accel[t, s][single.hidden])
                np.testing.assert_allclose(res.obs, res_b.obs[s], atol=1e-9)
                np.testing.assert_allclose(single.arc, arc[s], atol=1e-9)
                np.testing.assert_allclose(single.speed, speed[s], atol=1e-9)
                assert res.r_macro == pytest.approx(res_b.r_macro[s], abs=1e-9)
        finally:
            single.close()


def test_batched_core_takes_libsumo_back_on_a_full_reset(tmp_path):
    """libsumo runs one simulation per process: after another core took it, resetting every
    scene starts the batched core's own again and gives the same start; a partial step
    is refused with a one-line error."""
    sc = section_scenario(tmp_path, RING, EDGES, True)
    section = read_section(RING, EDGES, True)
    bank = synthetic_bank([0, 0], [100.0, 400.0], [12.0, 11.0], [True, False], horizon=4)
    core = BatchedSectionCore(sc, section, bank, RING, 2, seed=0)
    try:
        first = core.reset(np.zeros(2, dtype=np.int64))
        SectionCore(sc, section, bank, RING, seed=0).reset(0)  # takes libsumo over
        with pytest.raises(UserError, match="reset every scene"):
            core.step(np.zeros((2, 2)))
        np.testing.assert_array_equal(core.reset(np.zeros(2, dtype=np.int64)), first)
        res = core.step(np.full((2, 2), 0.5))
        assert res.stepped.all() and not res.truncated.any()
        np.testing.assert_allclose(res.obs[:, 0, 0], 12.25)  # v + a dt, SUMO's speed
    finally:
        core.close()


def test_vector_env_steps_every_sub_env_and_autoresets(small_ring_gt, tmp_path):
    """gymnasium VectorEnv over the batched core: batched spaces, rewards in (0, 1] while
    the episodes run, every sub-env truncated after H steps and restarted (reward 0, next
    episode's observation) by the step after."""
    path = write_scenario(tmp_path, SMALL_RING)
    env = SectionHiddenVectorEnv(4, path, small_ring_gt, seed=1)
    try:
        h = env.core.bank.horizon
        obs, _ = env.reset(seed=3)
        assert obs.shape == (4, env.core.obs_dim) and env.observation_space.contains(obs)
        assert env.action_space.shape == (4, 1)
        for t in range(h):
            obs, r, term, trunc, info = env.step(np.full((4, 1), -0.2, dtype=np.float32))
            assert not term.any() and (r > 0).all() and (r <= 1).all(), info["error"]
            assert trunc.all() == (t == h - 1)
        first = env.core.episode.copy()
        obs, r, term, trunc, _ = env.step(np.zeros((4, 1), dtype=np.float32))
        assert (r == 0).all() and not (term | trunc).any() and (env.core.t == 0).all()
        np.testing.assert_allclose(obs[:, 0], env.core.speed[np.arange(4), env._ego], rtol=1e-6)
        assert not np.array_equal(first, env.core.episode)
        with pytest.raises(ValueError, match="finite"):
            env.step(np.full((4, 1), np.nan))
    finally:
        env.close()

"""PPO's rollout on the batched env core is ``collect``'s on SectionCore, to the bit, and so
is a training on it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import torch
from policy_rings import ring_core, ring_scenario, true_state_bank

from macromicro_sumo.env.batched import BatchedSectionCore
from macromicro_sumo.env.observation import bank_shift_scale
from macromicro_sumo.env.section_observations import initial_observations
from macromicro_sumo.policy import ppo
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.policy.rollout import collect, collect_batched
from macromicro_sumo.truth.section import load_section


def test_batched_rollout_equals_collect_with_an_episode_ending_early(small_ring_gt, tmp_path):
    """Ten episodes, B = 4 (chunks of 4, 4, 2); episode 1 starts with two vehicles on one
    spot, so it collides and ends at its first step: the episodes after it in its chunk
    are run again on the noise collect gives them. Every array of the rollout is equal."""
    sc = ring_scenario(tmp_path, {})
    bank, _ = true_state_bank(sc, small_ring_gt)
    eps = np.arange(10) * 3 % len(bank)
    arc = bank.arc0_m.copy()
    arc[eps[1], 1] = arc[eps[1], 0]
    bank = dataclasses.replace(bank, arc0_m=arc)
    section = load_section(sc)[1]
    torch.manual_seed(0)
    agent = Agent(
        16, -1.0, sc.policy.observation, bank_shift_scale(initial_observations(sc, section, bank))
    )
    h = sc.policy.horizon
    core = ring_core(sc, bank)
    ref_gen = torch.Generator().manual_seed(5)
    try:
        ref = collect(agent, core, eps, 0.6, h, ref_gen)
    finally:
        core.close()
    batched = BatchedSectionCore(sc, section, bank, core.sim.options.net_file, 4, seed=0)
    try:
        gen = torch.Generator().manual_seed(5)
        got = collect_batched(agent, batched, eps, 0.6, h, gen)
    finally:
        batched.close()
    assert ref.collisions >= 1 and not ref.active[1, 1:].any()
    for f in dataclasses.fields(ref):
        np.testing.assert_array_equal(getattr(got, f.name), getattr(ref, f.name), err_msg=f.name)
    assert torch.equal(gen.get_state(), ref_gen.get_state())  # where collect left it


def test_training_on_the_batched_core_gives_the_same_policy(small_ring_gt, tmp_path, monkeypatch):
    """train_policy on the ring (its rollouts on the batched core) and with the batched core
    turned off (SectionCore, one episode at a time): the same weights and training log, to
    the bit, so the ring's results do not move."""
    sc = ring_scenario(tmp_path, {"policy.episodes_per_update": 6})
    bank, splits = true_state_bank(sc, small_ring_gt)
    fast = train_policy(sc, bank, tmp_path / "batched", progress=False, updates=2)
    monkeypatch.setattr(ppo, "batched_like", lambda core, b: None)
    slow = train_policy(sc, bank, tmp_path / "single", progress=False, updates=2)
    for k, v in slow["agent"].state_dict().items():
        assert torch.equal(fast["agent"].state_dict()[k], v), k
    logs = [pd.DataFrame(r["log"]).drop(columns="wall_s") for r in (fast, slow)]
    pd.testing.assert_frame_equal(*logs, check_exact=True)

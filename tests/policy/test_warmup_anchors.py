"""policy.residual's warm-up anchors: the start a deployment drives into (ring_two_lane's
fleet departs standing; real SUMO for the states, real torch for the loss), which no
snapshot episode and no recorded pair shows."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.observation import bank_shift_scale
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.demand_rollout import prior_warmup_states
from macromicro_sumo.policy.ppo import train_policy, warmup_anchors
from macromicro_sumo.policy.residual import (
    free_regime,
    off_support,
    pair_support,
    support_weight,
    warmup_anchor_loss,
)
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def start(tmp_path_factory: pytest.TempPathFactory):
    """ring_two_lane, one run of 60 s after a 40 s warm-up: the fitted Krauss-form prior,
    its pairs, and the warm-up's states under it (a few seconds of SUMO)."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(sc, simulation=replace(sc.simulation, n_runs=1, warmup_s=40.0, duration_s=60.0))
    folder = tmp_path_factory.mktemp("r2l_start")
    simulate_section(sc, folder / "gt", progress=False)
    truth = load_section_truth(folder / "gt", sc)
    prior, _, (obs, acc, _) = fit_residual_prior(sc, truth, np.array([0]))
    states = prior_warmup_states(sc, prior, lambda: DemandCore(sc, truth, truth.runs, 10))
    return sc, truth, prior, obs.astype(np.float32), states, acc


def test_the_warm_up_starts_standing_and_leaves_the_pairs(start):
    """Every step of the warm-up gives one row per driven vehicle; the first rows stand
    (the fleet departs at 0 m/s), behind a leader that stands too (delta_v 0), where no
    recorded pair is; later rows cruise inside the pairs' support."""
    sc, truth, prior, obs, states, _ = start
    assert warmup_anchors(sc, use_micro=True) and not warmup_anchors(sc, use_micro=False)
    steps = int(round(sc.simulation.warmup_s / sc.simulation.step_length_s)) - 1
    assert len(states) % steps == 0  # a closed ring: the same vehicles every step
    driven = len(states) // steps
    assert 0 < driven < 36  # the instrumented vehicles keep their own models
    first = states[:driven]
    assert np.abs(first[:, 0]).max() < 1.5  # m/s, one step after departing standing
    assert np.abs(first[:, 3]).max() < 1.5
    support = pair_support(torch.as_tensor(obs))
    scale = torch.as_tensor(bank_shift_scale(obs)[1], dtype=torch.float32)
    w = support_weight(torch.as_tensor(states), support, scale).numpy()
    assert (w[:driven] == 1.0).all()
    assert (w[-driven:] == 0.0).mean() > 0.8, (w[-driven:] == 0.0).mean()
    off = off_support(torch.as_tensor(states), support, scale)
    assert 0 < len(off) < len(states)
    agent = Agent(observation=sc.policy.observation, prior="krauss", prior_params=prior)
    assert bool(free_regime(agent, torch.as_tensor(first)).all())  # the prior's to drive


def test_warm_up_anchors_pull_the_start_to_the_prior_and_leave_the_pairs(start):
    """A residual of -0.3 m/s^2 everywhere (as the trained one left the standing start) is
    pulled to ~0 at the warm-up's states off the pairs; on the pairs inside their support
    the loss is 0 (the pairs and their own anchors set the residual there)."""
    sc, _, prior, obs, states, _ = start
    torch.manual_seed(0)
    agent = Agent(
        32,
        observation=sc.policy.observation,
        shift_scale=bank_shift_scale(obs),
        prior="krauss",
        prior_params=prior,
        residual_bound_mps2=1.0,
    )
    support = pair_support(torch.as_tensor(obs))
    warm = torch.as_tensor(states)
    off = off_support(warm, support, agent.scale)
    torch.nn.init.constant_(agent.actor[-1].bias, -0.3)
    pairs = torch.as_tensor(obs)
    inside = pairs[support_weight(pairs, support, agent.scale) == 0.0]
    assert len(inside) > 0.9 * len(pairs)
    with torch.no_grad():
        assert float(warmup_anchor_loss(agent, inside, support)) == 0.0
    opt = torch.optim.Adam(agent.actor.parameters(), lr=0.01)
    for _ in range(200):
        opt.zero_grad()
        warmup_anchor_loss(agent, off, support).backward()
        opt.step()
    with torch.no_grad():
        standing = agent.residual(off[off[:, 0] < 2.0])
    assert float(standing.abs().max()) < 0.05, float(standing.abs().max())


def true_completion(s):
    """The true hidden vehicles as the 'generated' ones, observed vehicles first."""
    order = np.argsort(np.where(s.valid, np.where(s.observed, 0, 1), 2), axis=1, kind="stable")
    take = lambda a: np.take_along_axis(a, order, 1)  # noqa: E731
    return take(s.lane), take(s.arc_m), take(s.speed_mps), take(s.valid), take(s.hidden)


def test_training_holds_the_standing_start_at_the_prior(start, tmp_path: Path):
    """PPO on ring_two_lane's snapshots with a residual that starts at -0.3 m/s^2: with the
    warm-up anchors the trained residual at the standing start is near 0 (the prior drives
    the start); without a warm-up (as the ring) no state is collected and the start keeps
    what the pairs' anchors leave there."""
    sc, truth, prior, obs, states, acc = start
    sc = replace(sc, policy=replace(sc.policy, episodes_per_update=4))
    torch.set_num_threads(1)
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_completion, 10, 0)
    net = scenario_inputs(sc).net_file

    def make_core(b, seed):
        return SectionCore(sc, truth.section, b, net, seed=seed)

    def make_demand():
        return DemandCore(sc, truth, truth.runs, 10)

    agent = Agent(
        sc.policy.hidden_size,
        observation=sc.policy.observation,
        prior="krauss",
        prior_params=prior,
        residual_bound_mps2=sc.policy.residual_bound_mps2,
    )
    torch.nn.init.constant_(agent.actor[-1].bias, -0.3)
    init = agent.state_dict()
    standing = torch.as_tensor(states[states[:, 0] < 2.0])
    out = {}
    for name, warm_s in (("warm-up", sc.simulation.warmup_s), ("none", 0.0)):
        run_sc = replace(sc, simulation=replace(sc.simulation, warmup_s=warm_s))
        res = train_policy(
            run_sc,
            bank,
            tmp_path / name,
            updates=3,
            progress=False,
            make_core=make_core,
            make_demand=make_demand,
            prior_params=prior,
            recorded_pairs=(obs, acc),
            init=init,
        )
        with torch.no_grad():
            out[name] = float(res["agent"].residual(standing).mean())
        assert ("warmup_states" in res) == (warm_s > 0)
    assert abs(out["warm-up"]) < 0.1, out
    assert out["none"] < out["warm-up"] - 0.05, out

"""The deployment's numpy actor (``deploy.policy_batch.actor_forward``, through ``policy_batch``):
its one product per layer up to ``ACTOR_ROWS`` vehicles, written into buffers kept between
calls, gives to the bit what fresh products give (the deployment's commands unchanged), and
an action it returned is not overwritten by the next call."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from macromicro_sumo.deploy.policy_batch import ACTOR_ROWS, policy_batch, prior_forward
from macromicro_sumo.policy.agent import Agent

IDM = {"speed_factor": 1.0, "tau_s": 1.2, "accel_mps2": 1.5, "decel_mps2": 2.0}
IDM |= {"min_gap_m": 2.0, "delta": 4.0, "veh_length_m": 5.0}


def fresh_products(agent: Agent, obs: np.ndarray) -> np.ndarray:
    """The actor as fresh arrays, ``ACTOR_ROWS`` rows a product (the actor before)."""
    x0 = (obs - agent.shift.double().numpy()) / agent.scale.double().numpy()
    out = np.empty(len(obs))
    for start in range(0, len(obs), ACTOR_ROWS):
        x = x0[start : start + ACTOR_ROWS]
        for m in agent.actor:
            if isinstance(m, torch.nn.Linear):
                w = m.weight.detach().double().numpy().T.copy()
                x = x @ w + m.bias.detach().double().numpy()
            else:
                x = np.tanh(x)
        out[start : start + ACTOR_ROWS] = x[:, 0]
    return out


@pytest.mark.parametrize("bound", [np.inf, 1.0, 2.5])
def test_the_numpy_actor_gives_fresh_products_to_the_bit(bound: float) -> None:
    torch.manual_seed(0)
    if np.isinf(bound):
        agent = Agent(64, observation="lookahead")
    else:  # a residual on the IDM, bounded
        agent = Agent(
            64, observation="lookahead", prior="idm", prior_params=IDM, residual_bound_mps2=bound
        )
        with torch.no_grad():  # a residual starts at 0: give it a trained-looking output
            agent.actor[-1].weight.normal_(0.0, 1.0)
            agent.actor[-1].bias.fill_(0.3)
    act = policy_batch(agent)
    rng = np.random.default_rng(1)
    kept = []
    for n in (0, 1, 45, 3, ACTOR_ROWS, ACTOR_ROWS + 1, 300, 45, 2 * ACTOR_ROWS):
        obs = np.column_stack(
            [rng.uniform(0, 30, n), np.full(n, 30.0), rng.uniform(5, 250, n)]
            + [rng.uniform(-5, 5, n), np.full(n, 30.0), rng.uniform(0, 500, n)]
        )
        want = fresh_products(agent, obs)
        if np.isfinite(bound):
            want = bound * np.tanh(want / bound) + prior_forward(agent)(obs)
        got = act(obs)
        assert got.shape == (n,) and got.dtype == np.float64
        assert np.array_equal(got.view(np.int64), want.view(np.int64)), n
        kept.append((got, want))
    for got, want in kept:  # later calls wrote into their own buffers, not into these
        assert np.array_equal(got.view(np.int64), want.view(np.int64))

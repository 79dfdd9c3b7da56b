"""The deployment's numpy actor (``deploy.policy_batch.actor_forward``, through ``policy_batch``):
its one product per layer up to ``ACTOR_ROWS`` vehicles, written into buffers kept between
calls, gives to the bit what fresh products give (the deployment's commands unchanged), and
an action it returned is not overwritten by the next call."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from macromicro_sumo.deploy.policy_batch import (
    ACTOR_ROWS,
    krauss_batch,
    policy_batch,
    prior_forward,
)
from macromicro_sumo.evaluation.krauss_fit import KraussParams, krauss_policy_accel
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


@pytest.mark.parametrize("relax_s", [0.2, 2.0])  # below the step (its max) and above
def test_the_krauss_batch_is_the_numpy_twin_to_the_bit(relax_s: float) -> None:
    """``krauss_batch`` (0-d constants, a product for the square) gives
    ``krauss_policy_accel``'s values to the bit: free, following, braking at the floor,
    no leader, a limit of 0 (the 0.1 m/s floor), a leader inside the minGap."""
    p = KraussParams(1.07, 1.9, 4.65, 1.09, 2.3, relax_s)
    batch = krauss_batch(p, 5.0, 0.5)
    rng = np.random.default_rng(7)
    for n in (0, 1, 5, 42, ACTOR_ROWS + 1, 300):
        obs = np.column_stack(
            [rng.uniform(0, 35, n), rng.choice([0.0, 13.9, 33.3], n), rng.uniform(5, 150, n)]
            + [rng.uniform(-3, 3, n), rng.uniform(0, 40, n), rng.uniform(0, 500, n)]
        )
        obs[: n // 4, 2] = 1e4  # no leader
        obs[n // 4 : n // 3, 2] = rng.uniform(-2, 9, n // 3 - n // 4)  # inside the minGap
        want = krauss_policy_accel(obs, p, 5.0, 0.5)
        got = batch(obs)
        assert got.shape == (n,) and got.dtype == np.float64
        assert np.array_equal(got.view(np.int64), want.view(np.int64)), n
        if n >= 42:  # the branches are all taken: free, behind a leader, the floor
            assert np.count_nonzero(got == p.accel_mps2) and np.count_nonzero(got == -9.0)
            assert np.count_nonzero((got > -9.0) & (got < p.accel_mps2))

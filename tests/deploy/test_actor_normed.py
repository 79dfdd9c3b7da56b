"""``actor_forward``'s float32 path writes the normalised observations into a buffer kept
between calls (the float64 quotient cast as it is written): the same actions to the bit as
the normalisation cast with astype, at every batch size and after the buffer grew."""

from __future__ import annotations

import numpy as np
import torch

from macromicro_sumo.deploy.policy_batch import ACTOR_ROWS, actor_forward
from macromicro_sumo.policy.agent import Agent


def _agent() -> Agent:
    torch.manual_seed(5)
    agent = Agent(64, observation="lookahead")
    with torch.no_grad():  # a normalisation of its own: the cast rounds the quotient
        agent.shift.copy_(torch.tensor([10.0, 30.0, 80.0, 0.5, 30.0, 200.0]))
        agent.scale.copy_(torch.tensor([7.0, 3.0, 60.0, 2.0, 3.0, 150.0]))
    return agent


def _astype_reference(agent: Agent, obs: np.ndarray) -> np.ndarray:
    """The float32 actor with the quotient cast by astype into a fresh array, each layer a
    fresh product and sum."""
    shift = agent.shift.detach().double().numpy()
    scale = agent.scale.detach().double().numpy()
    x = ((obs - shift) / scale).astype(np.float32)
    for m in agent.actor:
        if isinstance(m, torch.nn.Linear):
            w = np.ascontiguousarray(m.weight.detach().double().numpy().T, dtype=np.float32)
            x = x @ w + m.bias.detach().double().numpy().astype(np.float32)
        else:
            x = np.tanh(x)
    return x[:, 0].astype(np.float64)


def test_the_kept_normalisation_gives_astypes_actions_to_the_bit() -> None:
    agent = _agent()
    forward = actor_forward(agent, np.float32)
    rng = np.random.default_rng(2)
    # Small, then larger than the first buffer (it grows), then small again (a view of it),
    # and in chunks beyond ACTOR_ROWS.
    for n in (40, 10, 3 * ACTOR_ROWS // 4, 7, ACTOR_ROWS + 30, 40):
        obs = np.column_stack(
            [rng.uniform(0, 30, n), np.full(n, 30.0), rng.uniform(5, 250, n)]
            + [rng.uniform(-5, 5, n), np.full(n, 27.8), rng.uniform(0, 500, n)]
        )
        got = forward(obs)
        want = _astype_reference(agent, obs)
        assert got.dtype == np.float64 and got.shape == (n,)
        assert got.tobytes() == want.tobytes(), n
        # the float64 actor's values differ: the float32 path was taken
        assert np.count_nonzero(got != actor_forward(agent)(obs))

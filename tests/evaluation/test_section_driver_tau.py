"""Stage II's evaluation drives a policy trained with each driver's own tau
(``policy.driver_follow``, the agent's ``driver_tau`` buffer) with each hidden slot's seeded
tau as the last observation column, drawn as the training rollouts draw it
(``policy.driver_follow.follow_inputs``); a policy without the buffer sees no column.
Real SUMO (ring_two_lane, two runs of 40 s after a 30 s warm-up: tests/conftest.py's
``ring_driver_follow``) and real torch."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[1] / "policy"))
from test_warmup_anchors import true_completion  # noqa: E402

from macromicro_sumo.data.section import section_snapshots  # noqa: E402
from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS  # noqa: E402
from macromicro_sumo.env.driver_tau import with_tau  # noqa: E402
from macromicro_sumo.env.section import SectionCore  # noqa: E402
from macromicro_sumo.env.section_bank import build_section_bank  # noqa: E402
from macromicro_sumo.evaluation.section import agent_action, driven_bank  # noqa: E402
from macromicro_sumo.policy.agent import Agent, policy_action  # noqa: E402
from macromicro_sumo.policy.driver_follow import follow_inputs  # noqa: E402
from macromicro_sumo.sumo.inputs import scenario_inputs  # noqa: E402

TAU_Q = np.interp(QUANTILE_LEVELS, [0.0, 0.05, 0.5, 0.75, 0.95, 1.0],
                  [0.6, 0.8, 1.1, 1.4, 1.8, 2.2])  # fmt: skip


@pytest.fixture(scope="module")
def ring(ring_driver_follow):
    """tests/conftest.py's ring, its fitted prior and a bank of its snapshots."""
    sc, _, truth, prior, _, _ = ring_driver_follow
    bank = build_section_bank(sc, truth, section_snapshots(truth, sc, truth.runs),
                              true_completion, 10, 0)  # fmt: skip
    return sc, truth, prior, bank


def agent(sc, prior, taus: np.ndarray | None) -> Agent:
    return Agent(observation=sc.policy.observation, prior="krauss", prior_params=prior,
                 residual_bound_mps2=0.0, driver_tau=taus)  # fmt: skip


def test_the_evaluation_hands_each_hidden_slot_its_seeded_tau(ring) -> None:
    sc, truth, prior, bank = ring
    own, one = agent(sc, prior, TAU_Q), agent(sc, prior, None)
    driven = driven_bank(sc, truth, bank, own, seed=7)
    want = follow_inputs(bank, None, None, TAU_Q, 7)[0].driver_tau  # the training's draw
    np.testing.assert_array_equal(driven.driver_tau, want)
    assert np.unique(np.round(want, 6)).size > want.size // 2  # drawn, not one tau
    assert driven_bank(sc, truth, bank, one, seed=7) is bank  # no buffer: the bank as it is
    core = SectionCore(sc, truth.section, driven, scenario_inputs(sc).net_file, seed=0)
    ep = int(np.argmax(bank.hidden.sum(axis=1)))
    rng = np.random.default_rng(0)
    moved = 0
    try:
        obs = core.reset(ep)
        assert core.hidden.sum() >= 2
        for _ in range(8):
            got = agent_action(own, stochastic=False)(core, obs, rng)
            rows = torch.as_tensor(with_tau(obs, want[ep])[core.hidden], dtype=torch.float32)
            plain = torch.as_tensor(obs[core.hidden], dtype=torch.float32)
            with torch.no_grad():
                np.testing.assert_array_equal(got, own.mean_action(rows).numpy())
                single = one.mean_action(plain).numpy()
            # Without the buffer: the observation as it is, policy_action's own actions.
            np.testing.assert_array_equal(
                agent_action(one, stochastic=False)(core, obs, rng),
                policy_action(one, stochastic=False)(core, obs, rng),
            )
            moved += int(np.any(np.abs(got - single) > 1e-4))  # the slots' own taus
            obs = core.step(got).obs
    finally:
        core.close()
    assert moved >= 1

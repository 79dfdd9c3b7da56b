"""``policy.driver_follow`` in the deployment: each driven vehicle observes its own tau
as a trailing column (``deploy.observe.observe_rows`` with ``env.driver_tau.DriverTaus``),
the same in every run of a deployment, and the policy's prior brakes with it
(``deploy.policy_batch``); an agent without the ``driver_tau`` buffer (checkpoints from
before it) observes and drives as before. Real SUMO (game/cross, a red light), numpy and
torch priors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from red_light import CROSS, EDGES, red_light_queue

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS
from macromicro_sumo.env.driver_tau import (
    HANDOVER_RATE_S_PER_S,
    driver_tau_levels,
    supported_taus,
    taus_at,
)
from macromicro_sumo.evaluation.driver_follow import krauss_accel_per_driver
from macromicro_sumo.evaluation.krauss_fit import KraussParams
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.prior import prior_buffer
from macromicro_sumo.road.section import read_section
from macromicro_sumo.truth.section import record_run

# 502's drivers' taus (h2, stop 37): Krauss cars near 1.06 s, IDM cars at 1.4-1.8 s.
TAU_Q = np.interp(QUANTILE_LEVELS, [0.0, 0.05, 0.5, 0.75, 0.95, 1.0],
                  [1.0, 1.035, 1.075, 1.37, 1.79, 2.0])  # fmt: skip
# Draws longer than a queue's gaps support at the section's entry: the hand-over's.
LONG_Q = TAU_Q + 1.5


def agent(cross_krauss: dict, driver_tau: np.ndarray | None) -> Agent:
    """A Krauss residual policy (random actor: the residual is not 0) with or without the
    drivers' tau quantiles; the same weights either way."""
    torch.manual_seed(5)
    a = Agent(16, observation="lookahead", prior="krauss", prior_params=cross_krauss,
              residual_bound_mps2=1.0, driver_tau=driver_tau)  # fmt: skip
    for p in a.actor.parameters():
        torch.nn.init.normal_(p, std=0.3)
    return a


class Recorder(SectionSpeedDriver):
    """The deployment's driver, keeping every observation and command it made."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.rows: list[tuple[list[str], np.ndarray]] = []
        self.at_step: list[int] = []  # the step of each of ``rows``

    def observe(self, sim, vids, rows, st, *args, **kwargs):
        out = super().observe(sim, vids, rows, st, *args, **kwargs)
        self.rows.append((list(vids), out[0].copy()))
        self.at_step.append(self.steps)
        return out


def deploy_once(folder: Path, act) -> Recorder:
    folder.mkdir(parents=True, exist_ok=True)
    sc, sim = red_light_queue(folder, 4, 40.0)
    drv = Recorder(sc, read_section(CROSS, EDGES, False), 0, act, "sumo")
    try:
        record_run(sim, sc, drv.section, 0, drv)
    finally:
        sim.close()
    return drv


def test_each_driver_observes_its_own_tau_the_same_in_two_runs(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """Each driver's tau column is its draw, handed over (``DriverTaus.handed_over``): from
    the tau its first observed state supports where the draw is longer, up at
    ``HANDOVER_RATE_S_PER_S``; the same in two runs."""
    a = agent(cross_krauss, LONG_Q)
    act = policy_batch(a)
    first = deploy_once(tmp_path / "a", act)
    second = deploy_once(tmp_path / "b", act)
    assert len(first.rows) > 20
    seen: dict[str, list[tuple[int, float, np.ndarray]]] = {}
    for (vids, obs), step in zip(first.rows, first.at_step, strict=True):
        assert obs.shape[1] == 7  # lookahead's 6 features + the tau
        for v, o in zip(vids, obs, strict=True):
            seen.setdefault(v, []).append((step, o[-1], o[:6]))
    assert len(seen) == 4
    q = LONG_Q.astype(np.float32).astype(float)  # the agent's buffer is float32
    drawn = dict(
        zip(seen, taus_at(q, driver_tau_levels(first.sc.seed, 0, list(seen))), strict=True)
    )
    assert len(set(drawn.values())) == 4
    dt = first.sc.simulation.step_length_s
    held = 0
    for v, rows in seen.items():
        step0, tau0, obs0 = rows[0]
        ok = supported_taus(obs0[None, :], prior_buffer(a))[0]
        assert tau0 == min(drawn[v], max(ok, q[0]))
        held += tau0 < drawn[v]
        for step, tau, _ in rows:
            assert tau == min(drawn[v], tau0 + HANDOVER_RATE_S_PER_S * dt * (step - step0))
        assert rows[-1][1] == drawn[v] or rows[-1][0] - step0 < 2.0 / (HANDOVER_RATE_S_PER_S * dt)
    assert held >= 1  # a queue at a red light: some draws are longer than their gap supports
    assert [(v, o.tolist()) for v, o in first.rows] == [(v, o.tolist()) for v, o in second.rows]


def test_the_prior_brakes_with_each_rows_tau(cross_krauss: dict) -> None:
    """``policy_batch``'s numpy mean equals ``Agent.mean_action`` with the tau column, and
    its prior is ``krauss_accel_per_driver`` at those taus; a longer tau brakes harder."""
    a = agent(cross_krauss, TAU_Q)
    act = policy_batch(a)
    rng = np.random.default_rng(1)
    n = 64
    obs = np.column_stack([rng.uniform(10, 25, n), np.full(n, 25.0), rng.uniform(15, 60, n),
                           rng.uniform(-2, 4, n), np.full(n, 30.0), np.full(n, 500.0),
                           rng.uniform(1.0, 2.0, n)])  # fmt: skip
    with torch.no_grad():
        want = a.mean_action(torch.as_tensor(obs, dtype=torch.float64).float()).double().numpy()
    np.testing.assert_allclose(act(obs), want, atol=2e-4)
    p = {k: v for k, v in cross_krauss.items() if k not in ("veh_length_m", "dt_s")}
    prior = krauss_accel_per_driver(obs[:, :6], KraussParams(**p), obs[:, 6], 5.0, 0.5)
    alone = policy_batch(Agent(observation="lookahead", prior="krauss",
                               prior_params=cross_krauss, residual_bound_mps2=0.0,
                               driver_tau=TAU_Q))  # fmt: skip
    np.testing.assert_allclose(alone(obs), prior, atol=1e-5)  # the buffers are float32
    slow = obs.copy()
    slow[:, 6] = 2.0
    assert (alone(slow) <= alone(obs) + 1e-12).all() and (alone(slow) < alone(obs)).any()


def test_without_the_buffer_the_deployment_is_as_before(tmp_path: Path, cross_krauss: dict) -> None:
    """No ``driver_tau``: six columns, no ``driver_taus``, and the same commands as the
    one-tau prior's; a checkpoint's state_dict without the buffer loads and drives so."""
    old = agent(cross_krauss, None)
    act = policy_batch(old)
    assert act.driver_taus is None
    drv = deploy_once(tmp_path, act)
    assert all(obs.shape[1] == 6 for _, obs in drv.rows)
    loaded = agent(cross_krauss, None)
    loaded.load_state_dict(old.state_dict())
    assert loaded.driver_tau is None
    obs = np.concatenate([o for _, o in drv.rows])
    np.testing.assert_array_equal(policy_batch(loaded)(obs), act(obs))
    # With the buffer but an observation without the column: the one tau.
    with_q = agent(cross_krauss, TAU_Q)
    np.testing.assert_array_equal(policy_batch(with_q)(obs), act(obs))


def test_a_checkpoint_with_taus_loads_them_into_an_agent_made_without(cross_krauss) -> None:
    trained = agent(cross_krauss, TAU_Q)
    fresh = Agent(16, observation="lookahead", prior="krauss")
    fresh.load_state_dict(trained.state_dict())
    np.testing.assert_array_equal(fresh.driver_tau.numpy(), trained.driver_tau.numpy())
    obs = torch.tensor([[20.0, 25.0, 30.0, 1.0, 30.0, 500.0, 1.8]])
    assert fresh.mean_action(obs).item() == pytest.approx(trained.mean_action(obs).item())

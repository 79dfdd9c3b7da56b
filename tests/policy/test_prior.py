"""policy.prior = "idm": the policy's mean is a fitted IDM plus the actor's residual (real
torch, real SUMO on a small ring)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from policy_rings import gipps_agent, ring_scenario, true_state_bank

from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation import idm_fit
from macromicro_sumo.evaluation.idm_fit import (
    GippsParams,
    IdmParams,
    fit_policy_prior,
    gipps_policy_accel,
    idm_policy_accel,
)
from macromicro_sumo.policy import prior as prior_mod
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.policy.prior import idm_prior_params

PARAMS = IdmParams(speed_factor=1.05, tau_s=1.2, accel_mps2=1.4, decel_mps2=2.1, min_gap_m=2.5)
GIPPS = GippsParams(speed_factor=1.05, accel_mps2=1.7, decel_mps2=4.6, tau_s=1.1, min_gap_m=2.0)
LENGTH_M = 4.8
DT_S = 0.5


def _gipps_agent(observation: str = "lookahead", bound: float = 1.0) -> Agent:
    return gipps_agent(GIPPS, LENGTH_M, DT_S, observation=observation, residual_bound_mps2=bound)


def _obs(n: int, dim: int, seed: int = 0) -> np.ndarray:
    """Observations across the IDM's regimes: free road (no leader: a huge spacing), closing
    in, falling back, and spacings below the vehicle length (the gap floor)."""
    rng = np.random.default_rng(seed)
    obs = np.zeros((n, dim), dtype=np.float32)
    obs[:, 0] = rng.uniform(0.0, 40.0, n)
    obs[:, 1] = rng.choice([0.0, 13.9, 27.8, 44.4], n)  # 0: the desired speed's floor
    obs[:, 2] = np.concatenate(
        [rng.uniform(0.0, 8.0, n // 4), rng.uniform(0.0, 1000.0, n - n // 4)]
    )
    obs[:, 3] = rng.uniform(-10.0, 10.0, n)
    if dim > 4:
        obs[:, 4:] = rng.uniform(0.0, 200.0, (n, dim - 4))
    return obs


@pytest.mark.parametrize("dim", [4, 6])
def test_prior_mean_equals_idm_policy_accel(dim):
    observation = "paper" if dim == 4 else "lookahead"
    params = idm_prior_params(PARAMS.as_dict(), LENGTH_M)
    agent = Agent(16, observation=observation, prior="idm", prior_params=params)
    agent.actor.requires_grad_(False)
    obs = _obs(2000, dim)
    with torch.no_grad():
        mean = agent.mean_action(torch.as_tensor(obs)).numpy()
        dist_mean = agent.dist(torch.as_tensor(obs)).mean.numpy()
    want = idm_policy_accel(obs.astype(np.float64), PARAMS, LENGTH_M)
    # The residual starts at exactly 0: the untrained policy is the fitted IDM.
    np.testing.assert_allclose(mean, want, rtol=1e-4, atol=1e-3)
    np.testing.assert_array_equal(mean, dist_mean)
    assert want.min() == -idm_fit.EMERGENCY_DECEL_MPS2  # the braking bound was exercised
    # ...and the agent's prior brakes no harder than that bound either.
    assert mean.min() == pytest.approx(-prior_mod.EMERGENCY_DECEL_MPS2, abs=1e-3)


def test_no_prior_is_the_actor_alone():
    torch.manual_seed(0)
    agent = Agent(16, observation="lookahead")
    assert "idm_prior" not in agent.state_dict()
    obs = torch.as_tensor(_obs(50, 6))
    with torch.no_grad():
        actor = agent.actor((obs - agent.shift) / agent.scale).squeeze(-1)
        torch.testing.assert_close(agent.mean_action(obs), actor)
    with pytest.raises(UserError, match="policy.prior = 'ovm'"):
        Agent(16, prior="ovm")


@pytest.fixture(scope="module")
def ring(small_ring_gt, tmp_path_factory):
    folder = tmp_path_factory.mktemp("prior")
    sc = ring_scenario(folder, {"policy.episodes_per_update": 8, "policy.prior": "idm"})
    bank, _ = true_state_bank(sc, small_ring_gt)
    # Motorway-like parameters, not the ring's fit: the paper ring's slow, gentle IDM
    # (a = 0.28, b = 0.15 m/s^2) brakes at its bound at 51 m too when closing at 6 m/s.
    return sc, bank, idm_prior_params(PARAMS.as_dict(), sc.fleet.length_m)


@pytest.fixture(scope="module")
def trained(ring, tmp_path_factory):
    sc, bank, params = ring
    out = tmp_path_factory.mktemp("prior_policy")
    return train_policy(sc, bank, out, progress=False, updates=3, prior_params=params), out


def test_training_keeps_the_spacing_response(ring, trained):
    """At 30 m/s closing at 6 m/s (a 33.3 m/s limit), a trained policy with the prior brakes
    far harder at 5 m spacing than at 51 m: the response the actor alone did not learn."""
    res, _ = trained
    # lookahead's features: the next edge has the same limit, 500 m ahead.
    obs = torch.tensor([[30.0, 33.3, 51.0, 6.0, 33.3, 500.0], [30.0, 33.3, 5.0, 6.0, 33.3, 500.0]])
    obs = obs[:, : len(res["agent"].shift)]
    with torch.no_grad():
        far, near = res["agent"].mean_action(obs).tolist()
    assert near < far - 2.0, (far, near)


def test_checkpoint_round_trips_with_its_prior(ring, trained):
    sc, _, params = ring
    res, out = trained
    payload = torch.load(out / "policy.pt", weights_only=True)
    assert payload["prior"] == "idm"
    agent = load_policy(out / "policy.pt", sc)
    assert agent.prior == "idm"
    np.testing.assert_allclose(
        agent.idm_prior.numpy(), [params[k] for k in prior_mod.IDM_PRIOR_KEYS], rtol=1e-6
    )
    obs = torch.as_tensor(_obs(200, len(agent.shift), seed=1))
    with torch.no_grad():
        torch.testing.assert_close(agent.mean_action(obs), res["agent"].mean_action(obs))


def test_a_prior_mismatch_is_a_one_line_error(ring, trained, tmp_path):
    sc, bank, _ = ring
    _, out = trained
    plain = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, prior="none"))
    with pytest.raises(UserError, match="policy.prior = 'idm'") as err:
        load_policy(out / "policy.pt", plain)
    assert "\n" not in str(err.value)
    # A checkpoint from before the option (no "prior" recorded) was trained without one.
    payload = torch.load(out / "policy.pt", weights_only=True)
    del payload["prior"]
    torch.save(payload, tmp_path / "policy.pt")
    with pytest.raises(UserError, match="policy.prior = 'none'") as err:
        load_policy(tmp_path / "policy.pt", sc)
    assert "\n" not in str(err.value)
    # The prior's parameters come from the stage's fit: none is an error, not a NaN policy.
    with pytest.raises(UserError, match="needs its fitted parameters"):
        train_policy(sc, bank, tmp_path, progress=False, updates=1)


@pytest.mark.parametrize("bound", [0.0, 0.5, 1.0])
def test_the_residual_stays_within_its_bound(bound):
    """Whatever the actor outputs, the mean is within +-B of the IDM (B = 0: the IDM itself);
    near 0 the bounded residual is the actor's output (tanh's slope 1)."""
    params = idm_prior_params(PARAMS.as_dict(), LENGTH_M)
    torch.manual_seed(0)
    agent = Agent(
        16, observation="lookahead", prior="idm", prior_params=params, residual_bound_mps2=bound
    )
    last = agent.actor[-1]
    obs = torch.as_tensor(_obs(2000, 6, seed=2))
    idm = torch.as_tensor(idm_policy_accel(obs.numpy().astype(np.float64), PARAMS, LENGTH_M))
    with torch.no_grad():
        torch.nn.init.normal_(last.weight, std=30.0)  # outputs of several m/s^2 and more
        out = agent.actor((obs - agent.shift) / agent.scale).squeeze(-1)
        resid = agent.mean_action(obs).double() - idm
        assert out.abs().max() > 3.0 * max(bound, 1.0)
        assert resid.abs().max() <= bound + 1e-3
        if bound > 0:
            assert resid.abs().max() > 0.9 * bound  # the bound binds, not a zero residual
            last.weight.mul_(1e-4)
            small = agent.actor((obs - agent.shift) / agent.scale).squeeze(-1)
            resid = agent.mean_action(obs).double() - idm
            torch.testing.assert_close(resid, small.double(), rtol=1e-2, atol=2e-3)


def test_a_checkpoint_without_the_bound_loads_unbounded(ring, trained, tmp_path):
    """Residual policies trained before the bound had none: they load as they were trained."""
    sc, _, _ = ring
    _, out = trained
    payload = torch.load(out / "policy.pt", weights_only=True)
    assert float(payload["state_dict"]["residual_bound"]) == sc.policy.residual_bound_mps2
    del payload["state_dict"]["residual_bound"]
    torch.save(payload, tmp_path / "policy.pt")
    agent = load_policy(tmp_path / "policy.pt", sc)
    assert torch.isinf(agent.residual_bound)


@pytest.mark.parametrize("dim", [4, 6])
def test_gipps_prior_mean_equals_gipps_policy_accel(dim):
    agent = _gipps_agent("paper" if dim == 4 else "lookahead")
    obs = _obs(2000, dim, seed=3)
    with torch.no_grad():
        mean = agent.mean_action(torch.as_tensor(obs)).numpy()
    want = gipps_policy_accel(obs.astype(np.float64), GIPPS, LENGTH_M, DT_S)
    np.testing.assert_allclose(mean, want, rtol=1e-4, atol=1e-3)
    assert want.min() == -idm_fit.EMERGENCY_DECEL_MPS2
    # fit_policy_prior hands the agent its buffer in PRIOR_KEYS' order.
    obs4 = obs[:, :4].astype(np.float64)
    params, rmse = fit_policy_prior("gipps", obs4, want, LENGTH_M, DT_S)
    assert list(params) == list(prior_mod.GIPPS_PRIOR_KEYS) and rmse < 0.05
    assert params["dt_s"] == DT_S and params["veh_length_m"] == LENGTH_M


def _drive_to_a_wall(agent: Agent, v0: float, wall_m: float, seconds: float) -> tuple[float, float]:
    """Euler steps of DT_S of one car driven by the agent's mean action towards a standing
    obstacle ``wall_m`` ahead (as the env sees a lane end: a standing leader, delta_v = v);
    returns (the smallest bumper gap, the speed after the first 5 s)."""
    pos, v, least, v5 = 0.0, v0, np.inf, np.nan
    for step in range(int(seconds / DT_S)):
        spacing = wall_m - pos + LENGTH_M  # the wall's "back" at the line, a car length long
        obs = torch.tensor([[v, 33.3, spacing, v, 33.3, 1000.0]], dtype=torch.float32)
        with torch.no_grad():
            a = float(agent.mean_action(obs))
        v = max(0.0, v + a * DT_S)
        pos += v * DT_S
        least = min(least, wall_m - pos)
        if step + 1 == int(5.0 / DT_S):
            v5 = v
    return least, v5


def test_gipps_stops_before_a_wall_but_drives_on_towards_a_distant_one():
    """Physics, not numbers: a Gipps car at 30 m/s stops before a standing obstacle 120 m
    ahead without touching it; one entering an acceleration lane at 20 m/s with its end 200 m
    ahead speeds up over the first 5 s (SUMO's drivers do, then merge), where the IDM brakes
    for the lane end from the start (deployed ramp vehicles crawled to it and jammed)."""
    least, _ = _drive_to_a_wall(_gipps_agent(bound=0.0), 30.0, 120.0, 30.0)
    assert 0.0 <= least < 10.0
    _, v5 = _drive_to_a_wall(_gipps_agent(bound=0.0), 20.0, 200.0, 5.0)
    assert v5 > 22.0
    idm = Agent(
        16,
        observation="lookahead",
        prior="idm",
        prior_params=idm_prior_params(PARAMS.as_dict(), LENGTH_M),
        residual_bound_mps2=0.0,
    )
    _, v5_idm = _drive_to_a_wall(idm, 20.0, 200.0, 5.0)
    assert v5_idm < 20.0

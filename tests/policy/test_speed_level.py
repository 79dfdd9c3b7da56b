"""``deploy.speed_level`` (``policy.checkpoint.with_speed_level``): "tops" sets the Krauss
prior's speed factor to the median of the drivers' ratio estimate the agent carries, so a
deployed driver's desired speed is its drawn top speed; "fit" keeps the fitted one (real
torch; the scenario setting through the real loader)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import PAPER_SCENARIO

from macromicro_sumo.env.driver_speed_ratios import QUANTILE_LEVELS
from macromicro_sumo.errors import UserError
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.checkpoint import with_speed_level
from macromicro_sumo.policy.prior import KRAUSS_PRIOR_KEYS
from macromicro_sumo.scenario.load import load_scenario

# A fitted Krauss prior below its drivers' tops (drawn 522: 0.984 where the ratios' median is
# 1.016) and the drivers' ratio quantiles (normal, median 1.016).
PARAMS = dict(
    speed_factor=0.984,
    accel_mps2=2.6,
    decel_mps2=4.5,
    tau_s=1.0,
    min_gap_m=2.5,
    veh_length_m=5.0,
    dt_s=0.5,
    relax_s=2.0,
)
RATIOS = 1.016 + 0.1 * np.sqrt(2.0) * torch.erfinv(torch.as_tensor(2 * QUANTILE_LEVELS - 1))
RATIOS = np.clip(RATIOS.numpy(), 0.7, 1.3)
LIMIT_MPS = 24.0


def _agent(driver_speed: np.ndarray | None = RATIOS) -> Agent:
    params = {k: PARAMS[k] for k in KRAUSS_PRIOR_KEYS}
    return Agent(
        16, observation="paper", prior="krauss", prior_params=params, driver_speed=driver_speed
    )


def _free_accel(agent: Agent, v_mps: float) -> float:
    """The prior's acceleration on a free road (no leader within 1 km) at ``v_mps``."""
    obs = torch.tensor([[v_mps, LIMIT_MPS, 1000.0, 0.0]])
    with torch.no_grad():
        return float(agent.prior_accel(obs)[0])


def test_tops_sets_the_speed_factor_to_the_ratios_median():
    agent = with_speed_level(_agent(), "tops")
    median = float(np.interp(0.5, QUANTILE_LEVELS, agent.driver_speed.double().numpy()))
    assert median == pytest.approx(1.016, abs=1e-6)
    assert float(agent.krauss_prior[0]) == pytest.approx(median, abs=1e-6)
    # The other parameters are the fit's.
    np.testing.assert_allclose(
        agent.krauss_prior[1:].numpy(), [PARAMS[k] for k in KRAUSS_PRIOR_KEYS[1:]], rtol=1e-6
    )
    # At the fitted desired speed (0.984 x 24 = 23.6 m/s) the fitted prior cruises; with the
    # tops' level it still accelerates, towards 1.016 x 24 = 24.4 m/s, and cruises there.
    fitted = _agent()
    assert _free_accel(fitted, 0.984 * LIMIT_MPS) == pytest.approx(0.0, abs=1e-4)
    assert _free_accel(agent, 0.984 * LIMIT_MPS) > 0.3
    assert _free_accel(agent, median * LIMIT_MPS) == pytest.approx(0.0, abs=1e-3)


def test_fit_and_agents_without_the_quantiles_are_left_as_they_are():
    for agent, level in ((_agent(), "fit"), (_agent(None), "tops")):
        before = agent.krauss_prior.clone()
        assert torch.equal(with_speed_level(agent, level).krauss_prior, before)
    plain = Agent(16, observation="paper", driver_speed=RATIOS)  # no prior: nothing to set
    assert with_speed_level(plain, "tops") is plain and not hasattr(plain, "krauss_prior")


def test_the_setting_is_opt_in_and_checked():
    sc = load_scenario(PAPER_SCENARIO)
    assert sc.deploy.speed_level == "fit"
    said = load_scenario(PAPER_SCENARIO, {"deploy.speed_level": "fit"})
    tops = load_scenario(PAPER_SCENARIO, {"deploy.speed_level": "tops"})
    # Left out of the digest at the default: runs deployed before deploy as they were.
    assert said.digest() == sc.digest() != tops.digest()
    assert "speed_level" not in sc.to_dict()["deploy"]
    with pytest.raises(UserError, match="speed_level"):
        load_scenario(PAPER_SCENARIO, {"deploy.speed_level": "median"})

"""Who applies ``deploy.speed_level``: the deployment passes it to
``policy.checkpoint.load_policy``; every other reader of a checkpoint (Stage II's
evaluation, the refinement's judge, the scripts that score the policy as trained) calls
``load_policy`` without it and must get the policy as trained, whatever the scenario says
(the loader read the scenario's level itself until stop 50).
A real checkpoint file, loaded through the real loader, with a Krauss prior and the drivers'
ratio quantiles (real torch)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import PAPER_SCENARIO

from macromicro_sumo.env.driver_speed_ratios import QUANTILE_LEVELS, quantile_median
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.checkpoint import CHECKPOINT_FORMAT, load_policy, signature
from macromicro_sumo.policy.prior import KRAUSS_PRIOR_KEYS
from macromicro_sumo.scenario.load import load_scenario

FIT = dict(speed_factor=0.984, accel_mps2=2.6, decel_mps2=4.5, tau_s=1.0, min_gap_m=2.5)
FIT |= dict(veh_length_m=5.0, dt_s=0.5, relax_s=2.0)
# The drivers' top speed over the limit at QUANTILE_LEVELS, a median of 1.016 above the fit's
# 0.984 (drawn 522).
RATIOS = 1.016 + 0.1 * (QUANTILE_LEVELS - 0.5)


@pytest.fixture
def tops_checkpoint(tmp_path: Path):
    """A scenario saying ``deploy.speed_level = "tops"`` and a Krauss checkpoint for it."""
    sc = load_scenario(PAPER_SCENARIO, {"policy.prior": "krauss", "deploy.speed_level": "tops"})
    agent = Agent(
        16,
        observation=sc.policy.observation,
        prior="krauss",
        prior_params={k: FIT[k] for k in KRAUSS_PRIOR_KEYS},
        driver_speed=RATIOS,
    )
    payload = {
        "format": CHECKPOINT_FORMAT,
        "signature": signature(sc),
        "prior": "krauss",
        "hidden_size": 16,
        "state_dict": agent.state_dict(),
    }
    torch.save(payload, tmp_path / "policy.pt")
    return sc, tmp_path / "policy.pt"


def test_the_loader_keeps_the_trained_level_unless_the_deployment_asks(tops_checkpoint):
    sc, path = tops_checkpoint
    as_trained = load_policy(path, sc)
    deployed = load_policy(path, sc, sc.deploy.speed_level)
    assert float(as_trained.krauss_prior[0]) == pytest.approx(FIT["speed_factor"], abs=1e-6)
    assert float(deployed.krauss_prior[0]) == pytest.approx(quantile_median(RATIOS), abs=1e-6)
    assert quantile_median(RATIOS) > FIT["speed_factor"] + 0.02  # the two levels differ
    # Everything but the level is the checkpoint's.
    torch.testing.assert_close(deployed.krauss_prior[1:], as_trained.krauss_prior[1:])

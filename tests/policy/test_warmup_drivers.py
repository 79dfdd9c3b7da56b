"""The warm-up anchors' drivers (``policy.demand_rollout.prior_warmup_states``) each take
their own desired-speed factor (``policy.driver_speed``), as Stage II's demand episodes and
the deployment drive them (real SUMO: ring_two_lane, one run of 40 s after a 30 s warm-up)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.observed_drivers import driver_ratios
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.demand_rollout import prior_step, prior_warmup_states
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ring(tmp_path_factory: pytest.TempPathFactory):
    """ring_two_lane with policy.driver_speed = "drawn", one run of 40 s after a 30 s
    warm-up: the scenario, its truth, the fitted Krauss-form prior, the drivers' ratio
    quantiles."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(
        sc,
        simulation=replace(sc.simulation, n_runs=1, warmup_s=30.0, duration_s=40.0),
        policy=replace(sc.policy, driver_speed="drawn"),
    )
    folder = tmp_path_factory.mktemp("warmup_drivers")
    simulate_section(sc, folder / "gt", progress=False)
    truth = load_section_truth(folder / "gt", sc)
    prior, _, _ = fit_residual_prior(sc, truth, truth.runs)
    return sc, truth, prior, driver_ratios(sc, truth, truth.runs).quantiles


def test_the_warm_up_drives_each_driver_at_its_own_desired_speed(ring) -> None:
    """With policy.driver_speed = "drawn" the warm-up's states are those of the demand
    driven by the prior alone with the drivers' factors set (``set_driver_speeds``, as
    ``collect_demand`` and the deployment set them), step for step; they are not the states
    of drivers who all take the limits as they are (before: the warm-up set no factor)."""
    sc, truth, prior, quantiles = ring

    def make_demand() -> DemandCore:
        return DemandCore(sc, truth, truth.runs, 10)

    states = prior_warmup_states(sc, prior, make_demand, quantiles)

    agent = Agent(observation=sc.policy.observation, prior="krauss", prior_params=prior)

    def drive(factors: np.ndarray | None) -> np.ndarray:
        core = make_demand()
        core.set_driver_speeds(factors)
        out = []
        try:
            core.reset(0, core.dt)
            for _ in range(int(round(sc.simulation.warmup_s / core.dt)) - 1):
                o = prior_step(agent, core)
                if o is not None:
                    out.append(o)
        finally:
            core.close()
        return np.concatenate(out).astype(np.float32)

    # The agent carries the quantiles in float32 (its buffer), as the deployment reads them.
    own, plain = drive(quantiles.astype(np.float32).astype(float)), drive(None)
    assert states.shape == own.shape == plain.shape and len(states) > 100
    np.testing.assert_array_equal(states, own)
    assert np.abs(own - plain).max() > 0.1, "the drivers' factors changed nothing"
    assert not np.array_equal(states, plain)


def test_without_driver_speed_the_warm_up_is_as_before(ring) -> None:
    """policy.driver_speed = "none": every driver the limits as they are, quantiles or not."""
    sc, truth, prior, quantiles = ring
    sc = replace(sc, policy=replace(sc.policy, driver_speed="none"))

    def make_demand() -> DemandCore:
        return DemandCore(sc, truth, truth.runs, 10)

    plain = prior_warmup_states(sc, prior, make_demand)
    assert len(plain) > 50
    np.testing.assert_array_equal(plain, prior_warmup_states(sc, prior, make_demand, quantiles))

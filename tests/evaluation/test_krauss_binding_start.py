"""The Krauss-form fit where every observed driver keeps more than the starts' 1 s: Gipps' safe
speed binds on no pair at any start, so b, tau and min_gap have no gradient; one more start
with tau from the pairs' own time gaps finds them (ring_two_lane's IDM cars, docs/deploy-log.md,
"ring_two_lane (stop 29)")."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from macromicro_sumo.env.observed_drivers import krauss_pairs
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.evaluation.krauss_fit import (
    KraussParams,
    binding_start,
    fit_krauss,
    krauss_least_squares,
    krauss_policy_accel,
    network_defaults,
)
from macromicro_sumo.evaluation.micro_data import micro_pairs
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[2]
LENGTH_M = 5.0
DT_S = 0.5
LIMIT_MPS = 13.89
# Drivers that follow at 1.6 s and brake softly; the free term as SUMO's passenger car.
TRUE = KraussParams(
    speed_factor=1.0, accel_mps2=2.6, decel_mps2=2.5, tau_s=1.6, min_gap_m=1.0, relax_s=4.0
)
# The fit's stock start for the interaction (krauss_least_squares): b, tau, min_gap.
STOCK_START = (4.0, 1.0, 2.0)


def _steady_following(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of steady following at time gaps 1.5-2.6 s (none near 1 s), leaders within
    +-0.3 m/s, speeds 8-13 m/s: the accelerations ``TRUE`` gives plus 0.1 m/s^2 of noise."""
    rng = np.random.default_rng(seed)
    v = rng.uniform(8.0, 13.0, n)
    headway_s = rng.uniform(1.5, 2.6, n)
    spacing = LENGTH_M + TRUE.min_gap_m + v * headway_s
    dv = rng.uniform(-0.3, 0.3, n)
    obs = np.column_stack([v, np.full(n, LIMIT_MPS), spacing, dv])
    accel = krauss_policy_accel(obs, TRUE, LENGTH_M, DT_S) + rng.normal(0.0, 0.1, n)
    return obs, accel


@pytest.fixture(scope="module")
def ring_two_lane_pairs(tmp_path_factory: pytest.TempPathFactory):
    """ring_two_lane's observed pairs as the Krauss prior is fitted on them (one run of 300 s
    after the 120 s warm-up, ~2 s of SUMO), the speed factor held as the pipeline holds it
    where the drivers' ratios fall back (they do: a few cruise freely on the ring)."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(sc, simulation=replace(sc.simulation, n_runs=1, duration_s=300.0))
    folder = tmp_path_factory.mktemp("r2l")
    simulate_section(sc, folder / "gt", progress=False)
    truth = load_section_truth(folder / "gt", sc)
    runs = np.array([0])
    obs, accel = micro_pairs(sc, truth, runs)
    obs, accel, ratios = krauss_pairs(sc, truth, runs, obs, accel)
    assert ratios.fallback  # the premise: the speed factor is held
    return obs, accel, typical_length(truth), network_defaults(truth.vtypes)


def test_the_ring_s_idm_cars_give_the_safe_speed_s_parameters(ring_two_lane_pairs):
    """The IDM cars (T = 1.2 s, s0 = 2 m) brake softly long before a Krauss driver at 1 s
    would: from every stock start the safe speed binds on no pair and b, tau, min_gap stayed
    there (standard error inf), so the guard gave SUMO's 1 s. The binding start fits them:
    tau near the cars' time gaps, b below SUMO's 4.5 (soft braking), a lower cost, and the
    guard keeps them."""
    obs, accel, length, defaults = ring_two_lane_pairs
    held = {0: defaults.speed_factor}
    x, rmse, se = krauss_least_squares(obs, accel, length, DT_S, held)
    assert np.isfinite(se[2:4]).all()
    assert 1.2 < x[3] < 2.0 and x[2] < defaults.decel_mps2
    stock = np.array([defaults.speed_factor, x[1], *STOCK_START, x[5]])
    assert rmse < _rmse(obs, accel, stock, length)
    fit = fit_krauss(obs, accel, length, DT_S, defaults, {"speed_factor": "held"})
    assert not {"decel_mps2", "tau_s"} & set(fit.fallback)
    assert fit.params.tau_s == x[3] and fit.params.decel_mps2 == x[2]


def _rmse(obs: np.ndarray, accel: np.ndarray, x: np.ndarray, length: float) -> float:
    fitted = krauss_policy_accel(obs, KraussParams(*x), length, DT_S)
    return float(np.sqrt(np.mean((fitted - accel) ** 2)))


def test_the_binding_start_lies_among_the_followers_time_gaps():
    """tau's start makes the safe speed bind on the closest followers only; no start where
    no pair follows (a free road) or where their gaps are beyond the fit's range."""
    obs, _ = _steady_following(3000, seed=2)
    x = np.array([1.0, 2.6, *STOCK_START, 4.0])
    lower, upper = np.array([0.5, 0.1, 0.5, 0.1, 0.0, DT_S]), np.full(6, 20.0)
    start = binding_start(obs, x, LENGTH_M, lower, upper)
    assert start is not None
    assert np.array_equal(np.delete(start, 3), np.delete(x, 3))
    gaps_s = (obs[:, 2] - LENGTH_M - STOCK_START[2]) / obs[:, 0]
    assert 0.05 < np.mean(gaps_s < start[3]) < 0.2
    free_road = obs.copy()
    free_road[:, 2] = 1000.0
    assert binding_start(free_road, x, LENGTH_M, lower, upper) is None
    assert binding_start(obs, x, LENGTH_M, lower, np.full(6, 1.2)) is None

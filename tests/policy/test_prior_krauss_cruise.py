"""The Krauss prior's desired speed on a closed section whose drivers' ratios fall back
(ring_two_lane: few observed cars cruise freely, so the ratio estimate is SUMO's default,
median 1, while the speed factor is fitted all the same): the pairs are scaled over their
own drivers' median ratio, so the fitted speed factor is the typical observed driver's and a
deployed driver (factor 1) cruises where the observed cars cruise (docs/deploy-log.md,
"ring_two_lane's cruise (stop 31)"). Real SUMO: one run of ring_two_lane."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from macromicro_sumo.env.observed_drivers import krauss_pairs, observed_drivers
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.evaluation.krauss_fit import (
    KraussParams,
    krauss_least_squares,
    krauss_policy_accel,
    network_defaults,
)
from macromicro_sumo.evaluation.micro_data import micro_pairs
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[2]
DT_S = 0.5
# The free term alone is fitted here (speed factor, relax_s; a, b, tau, min_gap held): the
# interaction's parameters decide no cruising pair, and the full fit takes ~30 s.
HELD = {1: 2.6, 2: 2.3, 3: 1.65, 4: 0.0}
# A pair cruises: no leader within 2 s + 10 m (krauss_fit's free test), no faster than 1 m/s
# from the observed cars' typical 11-13 m/s.
CRUISE_MPS = (10.5, 13.0)


@pytest.fixture(scope="module")
def ring(tmp_path_factory: pytest.TempPathFactory):
    """ring_two_lane, one run of 300 s after its 120 s warm-up (~10 s of SUMO): its observed
    pairs, drivers, and the Krauss prior's pairs scaled both ways (own_median False: as on
    an open section, where the speed factor is held; True: as on a closed one)."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(sc, simulation=replace(sc.simulation, n_runs=1, duration_s=300.0))
    folder = tmp_path_factory.mktemp("r2l_cruise")
    simulate_section(sc, folder / "gt", progress=False)
    truth = load_section_truth(folder / "gt", sc)
    runs = np.array([0])
    obs, accel = micro_pairs(sc, truth, runs)
    scaled = {own: krauss_pairs(sc, truth, runs, obs, accel, own) for own in (False, True)}
    drivers = observed_drivers(sc, truth, runs)
    return sc, truth, runs, obs, accel, scaled, drivers


def _cruise_bias(params: KraussParams, obs: np.ndarray, accel: np.ndarray, length: float) -> float:
    """Mean prior minus recorded acceleration [m/s^2] over the cruising pairs, each as a
    deployed driver sees the road (limits unscaled)."""
    v, spacing = obs[:, 0], obs[:, 2]
    cruise = (v > CRUISE_MPS[0]) & (v < CRUISE_MPS[1]) & (spacing >= 2.0 * v + 10.0)
    prior = krauss_policy_accel(obs[cruise], params, length, DT_S)
    return float(np.mean(prior - accel[cruise]))


def test_pairs_are_scaled_over_their_own_drivers_median_where_the_speed_factor_is_fitted(ring):
    """Scaled over the fallback's median (1), every driver's limit shrinks by its ratio
    (below 1 on the ring: the cars' top speeds are under the limit), and a speed factor
    fitted to them is relative to limits a deployed driver never sees; scaled over their own
    median, the median driver keeps the limit as it is."""
    _, _, _, obs, _, scaled, drivers = ring
    own = np.median(list(drivers.ratio.values()))
    assert own < 0.99  # the premise: the observed cars' top speeds are below the limit
    held_obs, _, held = scaled[False]
    fit_obs, _, ratios = scaled[True]
    assert held.fallback and ratios.fallback == held.fallback
    assert held.pairs_median is None and "pairs_median" not in held.record()
    assert ratios.pairs_median == pytest.approx(own) and ratios.record()["pairs_median"] > 0
    limit = float(np.max(obs[:, 1]))
    assert np.median(fit_obs[:, 1]) == pytest.approx(limit, rel=0.02)
    assert np.median(held_obs[:, 1]) == pytest.approx(own * limit, rel=0.02)
    # Only the scale differs: the same pairs, the same speeds.
    np.testing.assert_array_equal(fit_obs[:, 0], held_obs[:, 0])
    np.testing.assert_allclose(fit_obs[:, 1] * own, held_obs[:, 1], rtol=1e-9)


def test_the_fitted_desired_speed_is_where_the_observed_cars_cruise(ring):
    """The free term fitted on each scaling, then applied to the unscaled pairs (as the
    deployment drives with driver_speed "none"): over the cruising pairs the recorded cars
    average no acceleration; the prior fitted on the fallback's scaling pulls them faster
    (its desired speed ~0.8 m/s above their cruise), on their own median's it stays within
    half of that."""
    _, truth, _, obs, accel, scaled, _ = ring
    length = typical_length(truth)
    assert network_defaults(truth.vtypes).accel_mps2 == HELD[1]
    bias = {}
    for own_median, (fit_obs, fit_acc, _) in scaled.items():
        x, _, _ = krauss_least_squares(fit_obs, fit_acc, length, DT_S, HELD)
        bias[own_median] = _cruise_bias(KraussParams(*x), obs, accel, length)
    print(bias)
    assert bias[False] > 0.05
    assert abs(bias[True]) < 0.5 * bias[False]


@pytest.mark.slow  # the full fit, ~30-40 s
def test_a_closed_sections_prior_records_the_median_its_pairs_are_scaled_over(ring):
    """fit_residual_prior on the closed ring: the speed factor is fitted (not held: nothing
    beyond a closed section holds its drivers back) on pairs scaled over their own median,
    and the policy manifest's record says which."""
    sc, truth, runs, _, _, _, drivers = ring
    _, extra, _ = fit_residual_prior(sc, truth, runs)
    record = extra["prior"]
    assert "speed_factor" in record["fitted"]
    ratios = record["driver_ratios"]
    assert ratios["fallback"] and ratios["median"] == 1.0
    own = np.median(list(drivers.ratio.values()))
    assert ratios["pairs_median"] == pytest.approx(own, abs=1e-4)

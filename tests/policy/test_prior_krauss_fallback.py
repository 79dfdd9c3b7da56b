"""policy.prior = "krauss" on a network nobody tuned it for: the parameters the observed pairs
do not identify fall back to SUMO's defaults for the network's vClass, and the policy manifest
says which and why (real SUMO: game/ramp's congested merge)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from conftest import game_ramp_truth
from test_prior_krauss import DT_S, KRAUSS, LENGTH_M, _pairs

from macromicro_sumo.env.observed_drivers import prior_pairs
from macromicro_sumo.evaluation.krauss_fit import (
    MIN_FREE_ACCEL_PAIRS,
    KraussParams,
    fit_krauss,
    krauss_least_squares,
    krauss_policy_accel,
    network_defaults,
    sumo_defaults,
)
from macromicro_sumo.pipeline.build import fit_residual_prior

# SUMO's passenger car (the ramp's vTypes set no accel or decel, so its cars drive with these).
SUMO_PASSENGER_ACCEL_MPS2 = 2.6


@pytest.fixture(scope="module")
def ramp_truth(tmp_path_factory: pytest.TempPathFactory):
    """game/ramp's main line, one run of 120 s after 300 s (the demand is past the merge's
    capacity from 300 s: a queue), half the vehicles observed (~8 s of SUMO)."""
    return game_ramp_truth(tmp_path_factory.mktemp("ramp"), "drawn")


def test_a_congested_merge_takes_sumos_free_acceleration_and_says_so(ramp_truth):
    """In the queue the observed cars rarely accelerate on a free road; the unguarded fit
    takes those held back by what they do not see for cars that barely accelerate. The
    guard gives a back SUMO's passenger default, which is what these cars drive with, keeps
    the identified parameters as fitted, and the manifest's record says why."""
    sc, truth = ramp_truth
    prior, extra, (obs, acc, _) = fit_residual_prior(sc, truth, truth.runs)
    record = extra["prior"]
    assert record["free_accel_pairs"] < MIN_FREE_ACCEL_PAIRS
    # Few cars cruise freely in the queue: their desired speeds are SUMO's too (the ratios'
    # fallback, env.driver_speed.ratio_estimate), the speed factor held at 1 in the fit.
    assert list(record["fallback"]) == ["speed_factor", "accel_mps2"]
    assert record["fallback"]["speed_factor"] == record["driver_ratios"]["fallback"] != ""
    assert prior["speed_factor"] == 1.0
    assert "free acceleration" in record["fallback"]["accel_mps2"]
    assert "accel_mps2" not in record["fitted"] and "decel_mps2" in record["fitted"]
    assert record["defaults"]["accel_mps2"] == SUMO_PASSENGER_ACCEL_MPS2  # vClass passenger
    assert prior["accel_mps2"] == SUMO_PASSENGER_ACCEL_MPS2
    # Unguarded, a is below what SUMO's Krauss does on a free road even with its dawdling
    # (a (1 - sigma U), 0.75 a on average at sigma 0.5).
    fit_obs, fit_acc = prior_pairs(sc, truth, truth.runs, obs, acc)
    x, _, _ = krauss_least_squares(fit_obs, fit_acc, record["veh_length_m"], DT_S, {0: 1.0})
    assert x[1] < 0.75 * SUMO_PASSENGER_ACCEL_MPS2
    unguarded = KraussParams(*x).as_dict()
    assert list(record["refitted"]) == ["relax_s"]  # fitted next to the rejected a
    for name in record["fitted"]:
        if name not in record["refitted"]:
            assert prior[name] == unguarded[name]


def test_a_well_identified_fit_is_the_unguarded_one():
    """Pairs with a tenth of the vehicles accelerating freely (as on Bremen) and close
    followers (8-60 m): nothing falls back, the parameters are the unguarded fit's, bit for
    bit. (At 20-150 m min_gap's standard error is half its value: it takes SUMO's 2.5 m.)"""
    obs, accel = _pairs(6000, seed=1, spacing_m=(8.0, 60.0))
    fit = fit_krauss(obs, accel, LENGTH_M, DT_S)
    assert fit.fallback == {} and fit.free_accel_pairs >= MIN_FREE_ACCEL_PAIRS
    assert fit.refitted == {} and fit.record()["refitted"] == {}
    x, rmse, _ = krauss_least_squares(obs, accel, LENGTH_M, DT_S)
    assert fit.params == KraussParams(*x) and fit.rmse_mps2 == rmse
    assert fit.params.accel_mps2 == pytest.approx(KRAUSS.accel_mps2, abs=0.15)


def test_parameters_no_pair_decides_fall_back_to_the_vclass_defaults():
    """A road on which no driver ever has a leader near: nothing shows how they follow, so
    the interaction parameters (b, tau, min_gap) take the defaults (a truck's, the vClass
    most vehicles have) while the free term's keep their fit; the RMSE is the returned
    parameters' own."""
    rng = np.random.default_rng(4)
    n = 4000
    v = np.concatenate([rng.uniform(0.9, 1.0, n // 2) * 30.0, rng.uniform(10.0, 28.0, n // 2)])
    obs = np.column_stack([v, np.full(n, 30.0 / 0.97), np.full(n, 1000.0), np.zeros(n)])
    accel = krauss_policy_accel(obs, KRAUSS, LENGTH_M, DT_S) + rng.normal(0.0, 0.3, n)
    vtypes = pd.DataFrame({"vclass": ["passenger", "truck"], "vehicles": [10, 30]})
    defaults = network_defaults(vtypes)
    assert defaults == sumo_defaults("truck") and defaults != sumo_defaults("passenger")
    fit = fit_krauss(obs, accel, LENGTH_M, DT_S, defaults)
    assert set(fit.fallback) >= {"decel_mps2", "tau_s"}
    assert "accel_mps2" not in fit.fallback and "speed_factor" not in fit.fallback
    assert fit.params.decel_mps2 == defaults.decel_mps2 and fit.params.tau_s == defaults.tau_s
    assert fit.params.accel_mps2 == pytest.approx(KRAUSS.accel_mps2, abs=0.1)
    want = krauss_policy_accel(obs, fit.params, LENGTH_M, DT_S)
    assert fit.rmse_mps2 == pytest.approx(float(np.sqrt(np.mean((want - accel) ** 2))))


def test_a_contradicted_by_the_free_acceleration_pairs_falls_back():
    """Enough pairs show free acceleration, but more pairs on a free-looking road do not
    accelerate (held back by a queue the observation does not see, as on a drawn net whose
    queue reaches its entry): the unguarded a serves those and is below what the free
    pairs show; the guard takes the default and says why."""
    rng = np.random.default_rng(6)
    limit = 30.0 / KRAUSS.speed_factor
    v_free = rng.uniform(10.0, 25.0, 1000)
    v_held = rng.uniform(3.0, 15.0, 3000)
    v = np.concatenate([v_free, v_held])
    spacing = np.full(len(v), 1000.0)  # the queue's tail is beyond the section's end
    obs = np.column_stack([v, np.full(len(v), limit), spacing, np.zeros(len(v))])
    accel = krauss_policy_accel(obs, KRAUSS, LENGTH_M, DT_S)
    accel[1000:] = 0.0  # the held-back pairs cruise in their queue
    accel += rng.normal(0.0, 0.3, len(v))
    x, _, _ = krauss_least_squares(obs, accel, LENGTH_M, DT_S)
    fit = fit_krauss(obs, accel, LENGTH_M, DT_S)
    assert fit.free_accel_pairs >= MIN_FREE_ACCEL_PAIRS
    assert x[1] < 1.0  # the unguarded a serves the held-back pairs
    assert "faster than the fit allows" in fit.fallback["accel_mps2"]
    assert fit.params.accel_mps2 == sumo_defaults().accel_mps2


def test_relax_fitted_next_to_a_rejected_a_is_refitted_alone():
    """Drivers below their desired speed close the gap slowly (relax_s 8 s), few accelerate
    freely, and those above it (a lower limit ahead, as on netgen_corridor) brake within
    ~1 s: the full fit serves both with a low a and a short relax_s. a falls back; kept next
    to it, the short relax_s would send the default a's cars at full acceleration towards
    their desired speed. Refitted alone (the others as fitted), it is long again, the fit's
    RMSE drops, and the record says so."""
    rng = np.random.default_rng(3)
    limit = 30.0
    v = np.concatenate([rng.uniform(0.8, 1.0, 3000), rng.uniform(1.0, 1.15, 1000)]) * limit
    obs = np.column_stack([v, np.full(len(v), limit), np.full(len(v), 1000.0), np.zeros(len(v))])
    slow = KraussParams(1.0, 2.6, 4.5, 1.0, 2.5, relax_s=8.0)
    accel = krauss_policy_accel(obs, slow, LENGTH_M, DT_S)
    above = v > limit
    brake = krauss_policy_accel(obs, replace(slow, relax_s=1.0), LENGTH_M, DT_S)
    accel[above] = brake[above]
    accel += rng.normal(0.0, 0.2, len(v))
    x, _, _ = krauss_least_squares(obs, accel, LENGTH_M, DT_S)
    assert x[1] < 1.0 and x[5] < 2.0  # low a, short relax_s
    fit = fit_krauss(obs, accel, LENGTH_M, DT_S)
    assert "free acceleration" in fit.fallback["accel_mps2"]
    assert fit.params.accel_mps2 == sumo_defaults().accel_mps2
    assert "relax_s" not in fit.fallback and "relax_s" in fit.fitted
    assert list(fit.refitted) == ["relax_s"] and fit.record()["refitted"] == fit.refitted
    assert "a fell back" in fit.refitted["relax_s"]
    assert fit.params.relax_s > 2.0 * x[5]
    assert fit.params.speed_factor == x[0]  # the others keep the full fit's values
    kept = replace(fit.params, relax_s=float(x[5]))

    def rmse(p: KraussParams) -> float:
        return float(np.sqrt(np.mean((krauss_policy_accel(obs, p, LENGTH_M, DT_S) - accel) ** 2)))

    assert fit.rmse_mps2 == pytest.approx(rmse(fit.params))
    assert fit.rmse_mps2 < 0.8 * rmse(kept)

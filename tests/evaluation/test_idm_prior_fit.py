"""The IDM prior's fit (``policy.prior = "idm"``) leaves out the pairs braking for a lower
limit ahead, which IDM's observation cannot see: it then recovers the drivers' IDM where a
fit to every pair takes them for drivers that barely accelerate."""

from __future__ import annotations

import numpy as np
import pytest

from macromicro_sumo.evaluation.idm_fit import (
    BELOW_DESIRED_SHARE,
    MIN_ACCEL_PAIRS,
    MIN_PRIOR_PAIRS,
    IdmParams,
    calibrate_idm,
    fit_policy_prior,
    idm_policy_accel,
)
from macromicro_sumo.road.physics import no_lower_limit_ahead

TRUE = IdmParams(speed_factor=0.95, tau_s=1.3, accel_mps2=1.0, decel_mps2=1.5, min_gap_m=2.5)
LENGTH_M = 5.0


def _lookahead_pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Ring-like pairs [v, limit, spacing, delta_v, next limit, distance to it]: IDM's
    acceleration where the next limit is not lower, else the braking towards the lower one
    that SUMO's drivers start far ahead of it (v^2 - v_next^2) / (2 distance), plus noise."""
    rng = np.random.default_rng(seed)
    limit = rng.choice([12.0, 13.0, 14.0], n)
    next_limit = rng.choice([12.0, 13.0, 14.0], n)
    v = rng.uniform(0.75, 1.05, n) * TRUE.speed_factor * limit
    spacing = LENGTH_M + rng.uniform(20.0, 150.0, n)
    dv = rng.normal(0.0, 0.8, n)
    dist = rng.uniform(1.0, 150.0, n)
    obs = np.stack([v, limit, spacing, dv, next_limit, dist], axis=1)
    accel = idm_policy_accel(obs[:, :4], TRUE, LENGTH_M)
    v_next = TRUE.speed_factor * next_limit
    lower = next_limit < limit
    brake = -np.clip((v**2 - v_next**2) / (2.0 * dist), 0.0, 1.5)
    accel = np.where(lower, np.minimum(accel, brake), accel) + rng.normal(0.0, 0.03, n)
    return obs, accel


def test_the_prior_fit_skips_the_pairs_before_a_lower_limit() -> None:
    obs, accel = _lookahead_pairs(3000, 0)
    keep = no_lower_limit_ahead(obs)
    assert keep.sum() == int((obs[:, 4] >= obs[:, 1]).sum()) >= MIN_PRIOR_PAIRS
    params, rmse = fit_policy_prior("idm", obs, accel, LENGTH_M, 0.5)
    assert rmse < 0.1
    assert params["accel_mps2"] == pytest.approx(1.0, rel=0.1)
    assert params["speed_factor"] == pytest.approx(0.95, abs=0.01)
    # Every pair: the braking ahead of a lower limit read as a weak free acceleration.
    every, _ = calibrate_idm(obs[:, :4], accel, LENGTH_M)
    assert abs(every.accel_mps2 - 1.0) > abs(params["accel_mps2"] - 1.0)


def test_without_a_look_ahead_or_with_too_few_pairs_every_pair_is_fitted() -> None:
    obs, accel = _lookahead_pairs(3000, 1)
    assert no_lower_limit_ahead(obs[:, :4]).all()
    few = np.flatnonzero(obs[:, 4] >= obs[:, 1])[: MIN_PRIOR_PAIRS - 1]
    mixed = np.concatenate([few, np.flatnonzero(obs[:, 4] < obs[:, 1])])
    from_lookahead, _ = fit_policy_prior("idm", obs[mixed], accel[mixed], LENGTH_M, 0.5)
    from_paper, _ = fit_policy_prior("idm", obs[mixed, :4], accel[mixed], LENGTH_M, 0.5)
    assert from_lookahead == pytest.approx(from_paper)


def _cruising_pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Free-road pairs of drivers each cruising at its own desired speed (factor 0.93-0.98
    of the limit, which the observation does not carry): nine in ten at it, the rest
    accelerating from up to 25% below it; IDM's acceleration with the driver's own factor,
    plus noise."""
    rng = np.random.default_rng(seed)
    limit = rng.choice([12.0, 13.0, 14.0], n)
    factor = rng.uniform(0.93, 0.98, n)
    below = np.where(rng.random(n) < 0.1, rng.uniform(0.0, 0.25, n), 0.0)
    v = factor * limit * (1.0 - below)
    spacing = rng.uniform(60.0, 220.0, n)  # the paper ring's: IDM's leader term ~0
    obs = np.stack([v, limit, spacing, rng.normal(0.0, 0.5, n), limit, np.full(n, 80.0)], axis=1)
    own = IdmParams(factor, TRUE.tau_s, TRUE.accel_mps2, TRUE.decel_mps2, TRUE.min_gap_m)
    return obs, idm_policy_accel(obs[:, :4], own, LENGTH_M) + rng.normal(0.0, 0.03, n)


def test_the_prior_refits_a_below_the_desired_speed() -> None:
    """A shared desired speed reads the drivers cruising at their own as weak acceleration:
    the one-step fit shrinks a; refitted on the pairs below the desired speed it is the
    drivers' a again, the rest of the fit kept."""
    obs, accel = _cruising_pairs(4000, 2)
    once, _ = calibrate_idm(obs[:, :4], accel, LENGTH_M)
    params, _ = fit_policy_prior("idm", obs, accel, LENGTH_M, 0.5)
    assert once.accel_mps2 < 0.9
    assert params["accel_mps2"] == pytest.approx(TRUE.accel_mps2, rel=0.05)
    assert params["speed_factor"] == pytest.approx(once.speed_factor)
    assert params["tau_s"] == pytest.approx(once.tau_s)
    # Too few pairs below the desired speed: the one-step fit stands.
    near = obs[:, 0] >= BELOW_DESIRED_SHARE * once.speed_factor * obs[:, 1]
    keep = np.flatnonzero(near)[: len(obs) // 2]
    keep = np.concatenate([keep, np.flatnonzero(~near)[: MIN_ACCEL_PAIRS - 1]])
    alone, _ = calibrate_idm(obs[keep, :4], accel[keep], LENGTH_M)
    params, _ = fit_policy_prior("idm", obs[keep], accel[keep], LENGTH_M, 0.5)
    assert params["accel_mps2"] == pytest.approx(alone.accel_mps2)

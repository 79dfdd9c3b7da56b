"""The IDM baseline's fit to observed pairs: it recovers known parameters, also when a few
pairs sit at a near-zero gap (a cut-in) with accelerations IDM cannot explain."""

from __future__ import annotations

import numpy as np
import pytest

from macromicro_sumo.evaluation.idm_fit import (
    EMERGENCY_DECEL_MPS2,
    GippsParams,
    IdmParams,
    calibrate_gipps,
    calibrate_idm,
    gipps_policy_accel,
    idm_policy_accel,
)

TRUE = IdmParams(speed_factor=0.95, tau_s=1.3, accel_mps2=1.2, decel_mps2=1.8, min_gap_m=2.5)
LENGTH_M = 5.0


def _pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    v = rng.uniform(2.0, 30.0, n)
    limit = rng.choice([13.9, 27.8, 33.3], n)
    spacing = LENGTH_M + rng.uniform(5.0, 120.0, n)
    dv = rng.normal(0.0, 1.5, n)
    obs = np.stack([v, limit, spacing, dv], axis=1)
    accel = idm_policy_accel(obs, TRUE, LENGTH_M) + rng.normal(0.0, 0.05, n)
    return obs, accel


def test_the_fit_recovers_the_parameters_that_made_the_pairs() -> None:
    obs, accel = _pairs(3000, 0)
    p, rmse = calibrate_idm(obs, accel, LENGTH_M)
    assert rmse < 0.1
    assert p.speed_factor == pytest.approx(0.95, abs=0.02)
    assert p.tau_s == pytest.approx(1.3, rel=0.1)
    assert p.accel_mps2 == pytest.approx(1.2, rel=0.1)
    assert p.decel_mps2 == pytest.approx(1.8, rel=0.2)


def test_a_few_pairs_at_a_near_zero_gap_do_not_drag_the_fit_onto_its_bounds() -> None:
    obs, accel = _pairs(3000, 1)
    cut = np.arange(0, 3000, 100)  # 1% cut-ins: 0.2 m or a negative gap, gentle braking
    obs[cut, 2] = LENGTH_M + np.linspace(-1.0, 0.2, len(cut))
    accel[cut] = -0.5
    p, rmse = calibrate_idm(obs, accel, LENGTH_M)
    assert np.isfinite(rmse) and rmse < 2.0
    assert p.tau_s == pytest.approx(1.3, rel=0.15)
    assert p.accel_mps2 == pytest.approx(1.2, rel=0.15)
    assert p.decel_mps2 < 5.0


def test_predicted_braking_is_bounded_by_the_emergency_deceleration() -> None:
    obs = np.array([[25.0, 27.8, LENGTH_M + 0.01, 10.0], [25.0, 27.8, LENGTH_M - 3.0, 0.0]])
    a = idm_policy_accel(obs, TRUE, LENGTH_M)
    assert np.all(np.isfinite(a)) and np.all(a >= -EMERGENCY_DECEL_MPS2)
    assert a[0] == pytest.approx(-EMERGENCY_DECEL_MPS2)


def test_the_gipps_fit_recovers_the_parameters_that_made_the_pairs() -> None:
    """Gipps' pairs: free driving and the safe speed both present (closing on a slower
    leader at short spacings), plus noise; a few outliers must not decide the fit."""
    true = GippsParams(speed_factor=1.05, accel_mps2=1.7, decel_mps2=4.5, tau_s=1.0, min_gap_m=2.5)
    rng = np.random.default_rng(4)
    n = 4000
    v = rng.uniform(2.0, 35.0, n)
    limit = rng.choice([13.9, 27.8, 33.3], n)
    spacing = LENGTH_M + np.where(rng.random(n) < 0.5, rng.uniform(3.0, 40.0, n), 250.0)
    dv = rng.normal(1.0, 3.0, n)
    obs = np.stack([v, limit, spacing, dv], axis=1)
    accel = gipps_policy_accel(obs, true, LENGTH_M, 0.5) + rng.normal(0.0, 0.05, n)
    accel[::200] = 3.0  # pairs no car-following model explains
    p, rmse = calibrate_gipps(obs, accel, LENGTH_M, 0.5)
    assert rmse < 1.0
    assert p.speed_factor == pytest.approx(1.05, abs=0.02)
    assert p.accel_mps2 == pytest.approx(1.7, rel=0.1)
    assert p.decel_mps2 == pytest.approx(4.5, rel=0.15)
    assert p.tau_s == pytest.approx(1.0, rel=0.15)

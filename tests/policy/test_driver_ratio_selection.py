"""Desired-speed ratios where which drivers cruise freely depends on their desired speed
(``env.driver_speed_ratios.spread_around_median``): on a queued road the slow drivers are
over-represented among the free ones, and many lower bounds are tops reached behind a
leader close to the driver's own desired speed. Kaplan-Meier alone then gave the bounds'
weight to the few fast exact ratios above them: its median rose and the slow exact ratios
became a slow tail of roadblocks (arterial 521: 9.2% of drawn factors below 0.8)."""

from __future__ import annotations

import numpy as np
from scipy.stats import norm

from macromicro_sumo.env.driver_speed import (
    QUANTILE_LEVELS,
    ObservedDrivers,
    censored_quantiles,
    factors_at,
    ratio_estimate,
    relative,
)

LEVELS = np.array([0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95])
TRUTH = 1.0 + 0.1 * norm.ppf(LEVELS)  # SUMO's speedFactor normc(1, 0.1) over its median


def _drivers(exact: np.ndarray, lower: np.ndarray) -> ObservedDrivers:
    ratio = {(0, f"e{i}"): float(r) for i, r in enumerate(exact)}
    bounds = {(0, f"l{i}"): float(r) for i, r in enumerate(lower)}
    return ObservedDrivers(ratio, np.empty((0, 4)), np.empty(0), [], bounds)


def _selected(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """4,000 drivers with ratios N(1, 0.1); a driver is exact with a chance falling with its
    ratio (0.15 at 1, 0.41 at 0.9, 0.06 at 1.1); of the others half reached near their own
    ratio (a bound 0-0.03 below it), half were queued (a bound 5-80% of it)."""
    rng = np.random.default_rng(seed)
    r = rng.normal(1.0, 0.1, 4000)
    exact = rng.random(4000) < np.clip(0.15 * np.exp(-10.0 * (r - 1.0)), 0.0, 1.0)
    near = rng.random(4000) < 0.5
    bound = np.where(near, r - rng.uniform(0.0, 0.03, 4000), r * rng.uniform(0.05, 0.8, 4000))
    return r[exact], bound[~exact]


def _relative(q: np.ndarray) -> np.ndarray:
    return np.interp(LEVELS, QUANTILE_LEVELS, relative(q))


def test_the_spread_around_the_median_recovers_the_generating_distribution():
    """The drawn factors' quantiles (ratio over the median) within 0.03 of the generating
    normal's, its slow tail (below 0.8) within a point of its 2.3%; Kaplan-Meier's were
    0.1 off, its tail three times too heavy (before: ``ratio_estimate`` returned it)."""
    for seed in (0, 1, 2):
        exact, lower = _selected(seed)
        est = ratio_estimate(_drivers(exact, lower))
        assert est.exact == len(exact) and est.lower_bounds == len(lower)
        assert np.abs(_relative(est.quantiles) - TRUTH).max() < 0.03
        km = censored_quantiles(exact, lower)
        assert np.abs(_relative(km) - TRUTH).max() > 0.06  # the premise
        levels = (np.arange(100_000) + 0.5) / 100_000
        slow = np.mean(factors_at(est.quantiles, levels) < 0.8)
        assert abs(slow - norm.cdf(-2.0)) < 0.01
        assert np.mean(factors_at(km, levels) < 0.8) > 3 * norm.cdf(-2.0)
        # A proper distribution: quantiles non-decreasing, the median Kaplan-Meier's.
        assert (np.diff(est.quantiles) >= 0).all()
        assert est.median == np.interp(0.5, QUANTILE_LEVELS, km)


def test_without_selection_or_bounds_the_estimate_is_as_before():
    """No bounds: the exact ratios' own quantiles; bounds below every exact ratio (queued
    cars) say nothing of the spread or the median: Kaplan-Meier's quantiles either way."""
    x = np.random.default_rng(3).normal(1.0, 0.1, 200)
    plain = censored_quantiles(x, np.empty(0))
    assert np.array_equal(ratio_estimate(_drivers(x, np.empty(0))).quantiles, plain)
    low = np.array([0.1, 0.2, 0.3])
    est = ratio_estimate(_drivers(x, low))
    assert np.allclose(est.quantiles, censored_quantiles(x, low))

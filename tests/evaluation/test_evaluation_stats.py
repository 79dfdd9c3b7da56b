"""The evaluation's paired bootstrap intervals."""

from __future__ import annotations

import numpy as np

from macromicro_sumo.evaluation.statistics import paired_bootstrap_ci, paired_bootstrap_std_ratio_ci


def test_bootstrap_interval_covers_the_mean_and_is_seeded() -> None:
    d = np.random.default_rng(0).normal(0.02, 0.1, 400)
    lo, hi = paired_bootstrap_ci(d, seed=3)
    assert lo < d.mean() < hi
    se = d.std() / np.sqrt(len(d))
    assert abs((hi - lo) - 2 * 1.96 * se) < 0.3 * (hi - lo)
    assert (lo, hi) == paired_bootstrap_ci(d, seed=3)
    assert np.isnan(paired_bootstrap_ci(np.array([np.nan, 1.0]), seed=3)[0])


def test_spacing_std_interval_covers_the_error_and_is_seeded() -> None:
    """Episodes (E, H, N) of spacings: a method that spreads every scene 5% more than the
    reference gets an interval around +5%; one that draws its own scenes from the same
    distribution gets an interval around 0 that is wider (its completions are noise)."""
    rng = np.random.default_rng(0)
    ref = rng.normal(125.0, 30.0, (350, 10, 5))
    wider = 125.0 + 1.05 * (ref - 125.0)
    wider[:20, 5:] = np.nan  # episodes that ended early count with the steps they have
    lo, hi = paired_bootstrap_std_ratio_ci(wider, ref, seed=1)
    assert lo < 5.0 < hi and hi - lo < 0.5
    assert (lo, hi) == paired_bootstrap_std_ratio_ci(wider, ref, seed=1)
    redraw = rng.normal(125.0, 30.0, ref.shape)
    lo, hi = paired_bootstrap_std_ratio_ci(redraw, ref, seed=1)
    assert lo < 0.0 < hi and 1.0 < hi - lo < 5.0
    assert np.isnan(paired_bootstrap_std_ratio_ci(ref[:1], ref[:1], seed=1)[0])

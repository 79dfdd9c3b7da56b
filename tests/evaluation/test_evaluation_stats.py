"""The evaluation's paired bootstrap interval and the report's per-figure verdicts."""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.evaluation.statistics import paired_bootstrap_ci, paired_bootstrap_std_ratio_ci
from macromicro_sumo.report.alignment import figure_winners


def test_bootstrap_interval_covers_the_mean_and_is_seeded() -> None:
    d = np.random.default_rng(0).normal(0.02, 0.1, 400)
    lo, hi = paired_bootstrap_ci(d, seed=3)
    assert lo < d.mean() < hi
    se = d.std() / np.sqrt(len(d))
    assert abs((hi - lo) - 2 * 1.96 * se) < 0.3 * (hi - lo)
    assert (lo, hi) == paired_bootstrap_ci(d, seed=3)
    assert np.isnan(paired_bootstrap_ci(np.array([np.nan, 1.0]), seed=3)[0])


def _row(method: str, v: float, lo: float, hi: float) -> dict:
    return {
        "K": 1,
        "method": method,
        "mean_speed_mps": 12.0 + v,
        "std_speed_mps": 0.5,
        "std_spacing_m": 30.0,
        "mean_speed_err_mps": abs(v),
        "speed_err_ci_lo_mps": lo,
        "speed_err_ci_hi_mps": hi,
    }


def test_overlapping_intervals_are_a_tie_and_separate_ones_a_win() -> None:
    gt = _row("ground_truth", 0.0, 0.0, 0.0)
    tie = pd.DataFrame(
        [gt, _row("policy", -0.01, -0.02, 0.0), _row("micro_only", 0.0, -0.01, 0.01)]
    )
    w = figure_winners(tie).set_index("figure")
    assert w.loc["mean-speed error (m/s)", "policy vs micro_only"].startswith("tie")
    assert w.loc["mean-speed error (m/s)", "best"] == "micro_only"
    win = pd.DataFrame(
        [gt, _row("policy", -0.05, -0.06, -0.04), _row("micro_only", 0.0, -0.01, 0.01)]
    )
    w = figure_winners(win).set_index("figure")
    assert w.loc["mean-speed error (m/s)", "policy vs micro_only"] == "micro_only"


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

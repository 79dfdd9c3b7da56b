"""Macro statistics of rollouts against the ground truth, for every road: the rows of
macro_alignment.csv, their paired-bootstrap intervals, and samples for histograms."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import wasserstein_distance

from macromicro_sumo.env.rollout import Rollouts

BOOTSTRAP_RESAMPLES = 2000


def w1(a: np.ndarray, b: np.ndarray) -> float:
    """Wasserstein-1 distance of two samples (in their unit), NaN if either is empty."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if not a.size or not b.size:
        return float("nan")
    return float(wasserstein_distance(a, b))


def paired_bootstrap_ci(
    diff: np.ndarray, seed: int, level: float = 0.95, resamples: int = BOOTSTRAP_RESAMPLES
) -> tuple[float, float]:
    """Percentile bootstrap interval of mean(diff) over paired episodes (resampled together)."""
    d = diff[np.isfinite(diff)]
    if len(d) < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng([seed, 7])
    means = d[rng.integers(0, len(d), (resamples, len(d)))].mean(axis=1)
    lo, hi = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def paired_bootstrap_std_ratio_ci(
    x: np.ndarray,
    ref: np.ndarray,
    seed: int,
    level: float = 0.95,
    resamples: int = BOOTSTRAP_RESAMPLES,
) -> tuple[float, float]:
    """Percentile bootstrap interval of 100 (std(x) / std(ref) - 1) [%], both pooled over
    all their finite values, resampling episodes (the first axis) together.

    Each episode's completion is a random draw, so this interval holds the noise of the
    completions and of the policy's actions on these scenes, which a single number hides.
    """

    def moments(a: np.ndarray) -> np.ndarray:
        a = a.reshape(len(a), -1)
        ok = np.isfinite(a)
        v = np.where(ok, a, 0.0)
        return np.stack([ok.sum(axis=1), v.sum(axis=1), (v * v).sum(axis=1)], axis=1)

    e = len(x)
    if e < 2 or e != len(ref):
        return float("nan"), float("nan")
    rng = np.random.default_rng([seed, 8])
    idx = rng.integers(0, e, (resamples, e))
    # How often each resample draws each episode, shared by both sides: (resamples, E).
    times = np.bincount((np.arange(resamples)[:, None] * e + idx).ravel(), minlength=resamples * e)
    times = times.reshape(resamples, e).astype(np.float64)

    def std(a: np.ndarray) -> np.ndarray:
        n, s1, s2 = (times @ moments(a)).T
        return np.sqrt(np.maximum(s2 / n - (s1 / n) ** 2, 0.0))

    pct = 100 * (std(x) / std(ref) - 1)
    lo, hi = np.quantile(pct, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def macro_row(
    labels: dict[str, Any], method: str, ro: Rollouts, ref: Rollouts | None, seed: int = 0
) -> dict[str, Any]:
    """One row of macro_alignment.csv, for any road: ``labels`` (the hidden-count source,
    and ``K`` where every snapshot is judged at every K) and the method's macro statistics over every vehicle
    on the road at every step. With ``ref`` (the ground truth on the same held-out
    snapshots, episode for episode) the errors against it and 95% paired-bootstrap
    intervals of the signed mean-speed error and of the spacing-std error in % (scenes,
    completions and action noise of this evaluation; not the training seed's noise)."""
    v, d, a = ro.speed_mps, ro.spacing_m, ro.accel_mps2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an episode that ended at once
        row: dict[str, Any] = {
            **labels,
            "method": method,
            "mean_speed_mps": float(np.nanmean(v)),
            "std_speed_mps": float(np.nanstd(v)),
            "mean_spacing_m": float(np.nanmean(d)),
            "std_spacing_m": float(np.nanstd(d)),
            "vehicles_per_step": float(np.isfinite(v).sum() / max(1, v[:, :, 0].size)),
            "collisions": ro.collisions,
            "episodes": len(v),
            "sumo_errors": ro.errors,
        }
    if ref is None:
        return row

    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        diff = np.nanmean(v, axis=(1, 2)) - np.nanmean(ref.speed_mps, axis=(1, 2))
        ref_speed, ref_speed_std = np.nanmean(ref.speed_mps), np.nanstd(ref.speed_mps)
        ref_spacing, ref_spacing_std = np.nanmean(ref.spacing_m), np.nanstd(ref.spacing_m)
    lo, hi = paired_bootstrap_ci(diff, seed)
    s_lo, s_hi = paired_bootstrap_std_ratio_ci(d, ref.spacing_m, seed)
    row.update(
        mean_speed_err_mps=abs(row["mean_speed_mps"] - ref_speed),
        speed_err_ci_lo_mps=lo,
        speed_err_ci_hi_mps=hi,
        std_speed_ratio=row["std_speed_mps"] / ref_speed_std,
        mean_spacing_ratio=row["mean_spacing_m"] / ref_spacing,
        std_spacing_ratio=row["std_spacing_m"] / ref_spacing_std,
        spacing_std_err_pct=100 * (row["std_spacing_m"] / ref_spacing_std - 1),
        spacing_std_err_ci_lo_pct=s_lo,
        spacing_std_err_ci_hi_pct=s_hi,
        w1_speed_mps=w1(v.ravel(), ref.speed_mps.ravel()),
        w1_accel_mps2=w1(a.ravel(), ref.accel_mps2.ravel()),
        w1_spacing_m=w1(d.ravel(), ref.spacing_m.ravel()),
    )
    return row


def samples_frame(
    labels: dict[str, Any], method: str, ro: Rollouts, max_episodes: int = 100
) -> pd.DataFrame:
    """A sample of rollout states for histograms (first ``max_episodes`` episodes)."""
    e = min(max_episodes, len(ro.speed_mps))
    v, d = ro.speed_mps[:e].ravel(), ro.spacing_m[:e].ravel()
    ok = np.isfinite(v)
    return pd.DataFrame({**labels, "method": method, "speed_mps": v[ok], "spacing_m": d[ok]})

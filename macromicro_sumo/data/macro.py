"""Macroscopic statistics: the descriptor Psi and its estimators (the loss terms on it:
``data.objective``).

Two estimators of the same quantities, per run and aggregation interval:

* ``source=trajectories`` (the truth): pooled over every vehicle and recorded step in the
  interval. Mean speed is the space-mean speed (all vehicles at each instant); density is
  N / L; flow = density x mean speed.
* ``source=detectors`` (what a roadside operator has):
  - mean speed: space-mean speed from the E2 lane-area detectors covering the ring,
    sum(meanSpeed x sampledSeconds) / sum(sampledSeconds);
  - density: vehicles present on each E2, sum(sampledSeconds) / T, corrected for the
    vehicle length (a vehicle occupies an E2 of length l for (l + l_veh) / v seconds,
    l_veh measured by the E1 loops), summed over the ring and divided by L;
  - mean spacing: 1000 / density; flow: mean E1 flow (veh/h);
  - speed std, v_min, v_max: from per-vehicle speeds at the instantaneous loops (a
    time-mean sample);
  - spacing std, d_min, d_max: from per-vehicle time headways at the instantaneous loops
    times speed (mean of the two passage speeds), as a loop in the field measures them.

Psi(S) = [mean speed, mean spacing, d_min, d_max, v_min, v_max] (PSI_COLUMNS).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

PSI_COLUMNS = [
    "mean_speed_mps",
    "mean_spacing_m",
    "spacing_min_m",
    "spacing_max_m",
    "speed_min_mps",
    "speed_max_mps",
]

MACRO_COLUMNS = [
    "run",
    "source",
    "begin_s",
    "end_s",
    *PSI_COLUMNS,
    "speed_std_mps",
    "spacing_std_m",
    "density_vehpkm",
    "flow_vehph",
    "n_samples",
]


def extended_bounds(lo: Any, hi: Any, n: Any) -> tuple[Any, Any]:
    """[lo, hi], the extremes of n samples, widened by (hi - lo) / (n - 1) on each side
    (``generator.bounds_source = "extended"``, ring and sections): n draws' range covers on
    average (n - 1) / (n + 1) of the distribution, and range / (n - 1) each side is the
    classical correction of the ends. Crossed bounds stay as measured; n < 2 counts as 2."""
    widen = np.maximum(np.subtract(hi, lo), 0.0) / (np.maximum(n, 2.0) - 1.0)
    return lo - widen, hi + widen


def _intervals(interval_s: float, duration_s: float) -> list[tuple[float, float]]:
    n = int(np.floor(duration_s / interval_s + 1e-9))
    return [(k * interval_s, (k + 1) * interval_s) for k in range(n)]


def trajectory_macro(
    traj: pd.DataFrame, length_m: float, interval_s: float, duration_s: float
) -> pd.DataFrame:
    """The true macro statistics per run and interval, from recorded trajectories."""
    rows = []
    for run, g in traj.groupby("run", sort=True):
        t = g["time_s"].to_numpy()
        n_veh = g["vehicle_id"].nunique()
        for begin, end in _intervals(interval_s, duration_s):
            w = g[(t >= begin - 1e-9) & (t < end - 1e-9)]
            if w.empty:
                continue
            v, d = w["speed_mps"].to_numpy(), w["spacing_m"].to_numpy()
            density = n_veh / length_m * 1000.0
            rows.append(
                {
                    "run": run,
                    "source": "trajectories",
                    "begin_s": begin,
                    "end_s": end,
                    "mean_speed_mps": v.mean(),
                    "mean_spacing_m": d.mean(),
                    "spacing_min_m": d.min(),
                    "spacing_max_m": d.max(),
                    "speed_min_mps": v.min(),
                    "speed_max_mps": v.max(),
                    "speed_std_mps": v.std(),
                    "spacing_std_m": d.std(),
                    "density_vehpkm": density,
                    "flow_vehph": density * v.mean() * 3.6,
                    "n_samples": len(w),
                }
            )
    return pd.DataFrame(rows, columns=MACRO_COLUMNS)


def passage_spacings(passages: pd.DataFrame) -> pd.DataFrame:
    """Spacing estimates from consecutive passages at each instantaneous loop.

    Spacing = time headway x mean of the two passage speeds: the distance the leader
    covered between its passage and the follower's, for near-constant speeds.
    """
    out = []
    for _, g in passages.sort_values(["run", "detector_id", "time_s"]).groupby(
        ["run", "detector_id"]
    ):
        t, v = g["time_s"].to_numpy(), g["speed_mps"].to_numpy()
        if len(t) < 2:
            continue
        out.append(
            pd.DataFrame(
                {
                    "run": g["run"].to_numpy()[1:],
                    "detector_id": g["detector_id"].to_numpy()[1:],
                    "time_s": t[1:],
                    "spacing_m": np.diff(t) * 0.5 * (v[1:] + v[:-1]),
                }
            )
        )
    cols = ["run", "detector_id", "time_s", "spacing_m"]
    return pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=cols)


def detector_macro(det: pd.DataFrame, passages: pd.DataFrame, length_m: float) -> pd.DataFrame:
    """Macro statistics per run and interval as the loop detectors estimate them."""
    spacings = passage_spacings(passages)
    rows = []
    for (run, begin, end), g in det.groupby(["run", "begin_s", "end_s"], sort=True):
        e1, e2 = g[g["kind"] == "E1"], g[g["kind"] == "E2"]
        ss = e2["sampled_seconds_s"].to_numpy()
        mean_speed = (
            float(np.nansum(e2["speed_mps"].to_numpy() * ss) / ss.sum()) if ss.sum() > 0 else np.nan
        )
        veh_len = (
            float(np.nanmean(e1["mean_length_m"])) if e1["mean_length_m"].notna().any() else 0.0
        )
        det_len = e2["detector_length_m"].to_numpy()
        present = ss / (end - begin) * det_len / (det_len + veh_len)
        density = present.sum() / length_m * 1000.0
        p = passages[
            (passages["run"] == run) & (passages["time_s"] >= begin) & (passages["time_s"] < end)
        ]
        s = spacings[
            (spacings["run"] == run) & (spacings["time_s"] >= begin) & (spacings["time_s"] < end)
        ]
        v, d = p["speed_mps"].to_numpy(), s["spacing_m"].to_numpy()
        # Sample std (ddof = 1): an interval holds ~20 passages, and the population form
        # understates the stream's variance by 1/n (pooled spacing std 31.2 vs 31.9 m from
        # trajectories on ring_paper; 31.9 with ddof = 1).
        rows.append(
            {
                "run": run,
                "source": "detectors",
                "begin_s": begin,
                "end_s": end,
                "mean_speed_mps": mean_speed,
                "mean_spacing_m": 1000.0 / density if density > 0 else np.nan,
                "spacing_min_m": d.min() if d.size else np.nan,
                "spacing_max_m": d.max() if d.size else np.nan,
                "speed_min_mps": v.min() if v.size else np.nan,
                "speed_max_mps": v.max() if v.size else np.nan,
                "speed_std_mps": v.std(ddof=1) if v.size > 1 else np.nan,
                "spacing_std_m": d.std(ddof=1) if d.size > 1 else np.nan,
                "density_vehpkm": density,
                "flow_vehph": float(e1["flow_vehph"].mean()),
                "n_samples": len(p),
            }
        )
    return pd.DataFrame(rows, columns=MACRO_COLUMNS)

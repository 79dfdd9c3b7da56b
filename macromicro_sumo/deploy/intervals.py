"""Detector intervals pooled into the deployment's comparison interval
(``deploy.compare_interval_s``; docs/deploy.md, "GEH").

GEH < 5 for more than 85% of the counts (UK DMRB, TAG M3.1) is a criterion for hourly
flows. A deployment's detectors aggregate over ``detectors.interval_s`` (Bremen: 30 s, so
that the hidden-count estimate follows the merge's waves), where one vehicle is 120 veh/h
and the test measures when each car passes as much as the flow. Pooling every detector's
intervals into blocks of the comparison interval keeps the per-interval definitions of
docs/deploy.md ("Flow, speed, density of a station"), so that ``deploy.compare``'s station
table reads a pooled ``detectors.csv`` as it reads SUMO's own:

- counts (``n_veh``) and E2 sampled seconds add up; the flow is the block's count as an
  hourly rate (the intervals' flows weighted by their lengths);
- E1 speed: the harmonic mean of every vehicle that passed, n / sum(n_i / v_i) (a loop's
  interval speed is already the harmonic mean of its vehicles); E2 speed: the mean weighted
  by the seconds vehicles spent on the detector;
- density and occupancy: the mean over the block's intervals. For an E1 loop (density =
  flow / speed / 3.6, 0 where nothing passed) this is the pooled flow / pooled speed / 3.6.

Blocks are [j P, (j + 1) P) from t = 0, the grid SUMO's loops aggregate on; only whole
blocks are kept (a run of 720 s gives two blocks of 300 s, its last 120 s are not compared).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError

KEY = "deploy.compare_interval_s"
DETECTOR = ["run", "detector_id", "kind", "lane_index", "arc_m"]
GRID_TOLERANCE = 1e-6  # [fraction of an interval] float slack of begin_s / period


def interval_length_s(table: pd.DataFrame) -> float:
    """The most common interval length [s] of a table with ``begin_s`` and ``end_s``
    (``detectors.csv``: the detectors' period; a comparison: its interval)."""
    length = (table["end_s"] - table["begin_s"]).round(3)
    return float(length.mode().max())


def block_factor(interval_s: float, detector_s: float, where: str) -> int:
    """How many detector intervals make one comparison interval (0: the detectors' own, 1).
    Anything but a whole multiple of the detectors' period is refused in one line."""
    if interval_s == 0:
        return 1
    k = interval_s / detector_s
    if k < 1 - GRID_TOLERANCE or abs(k - round(k)) > GRID_TOLERANCE:
        raise UserError(
            f"{where}: {KEY} = {interval_s:g} is not a multiple of the detectors' interval "
            f"{detector_s:g} s; accepted: 0 (the detectors' own) or k x {detector_s:g} s, "
            "k = 1, 2, ..."
        )
    return round(k)


def pool_detectors(det: pd.DataFrame, k: int) -> pd.DataFrame:
    """``det`` (rows of ``detectors.csv``) with every detector's intervals pooled in whole
    blocks of k (module docstring), in the same columns; the partial interval SUMO writes
    when a run ends is left out first."""
    period = interval_length_s(det)
    length = (det["end_s"] - det["begin_s"]).round(3)
    d = det[length >= period - 1e-6].copy()
    d["block"] = np.floor(d["begin_s"] / (k * period) + GRID_TOLERANCE).astype(int)
    group = [*(c for c in DETECTOR if c in d.columns), "block"]
    d = d[d.groupby(group, dropna=False)["begin_s"].transform("size") == k]
    v = d["speed_mps"].to_numpy(float)
    n = d["n_veh"].to_numpy(float)
    ss = (
        d["sampled_seconds_s"].fillna(0.0).to_numpy(float)
        if "sampled_seconds_s" in d
        else np.zeros(len(d))
    )
    passed = np.isfinite(v) & (v > 0) & (n > 0)
    timed = np.isfinite(v) & (ss > 0)
    seconds = (d["end_s"] - d["begin_s"]).to_numpy(float)
    d = d.assign(
        w_count=d["flow_vph"] * seconds / 3600.0,
        w_n=np.where(passed, n, 0.0),
        w_inv=np.where(passed, n / np.where(passed, v, 1.0), 0.0),
        w_ss=np.where(timed, ss, 0.0),
        w_ssv=np.where(timed, ss * np.where(timed, v, 0.0), 0.0),
    )
    # Every interval of a block must hold a value for the block to hold one (min_count = k).
    spec: dict[str, tuple[str, object]] = {
        "begin_s": ("begin_s", "min"),
        "end_s": ("end_s", "max"),
        "n_veh": ("n_veh", lambda x: x.sum(min_count=k)),
        "w_count": ("w_count", lambda x: x.sum(min_count=k)),
        "density_vpkm": ("density_vpkm", lambda x: x.mean() if x.notna().all() else np.nan),
        **{f"w_{w}": (f"w_{w}", "sum") for w in ("n", "inv", "ss", "ssv")},
    }
    for col in ("occupancy_pct", "sampled_seconds_s"):
        if col in d:
            spec[col] = (col, "mean" if col == "occupancy_pct" else "sum")
    for col in d.columns.difference([*group, *spec, "flow_vph", "speed_mps"]):
        if not col.startswith("w_"):
            spec[col] = (col, "first")
    out = d.groupby(group, dropna=False, sort=False).agg(**spec).reset_index()
    out["flow_vph"] = out["w_count"] * 3600.0 / (out["end_s"] - out["begin_s"])
    with np.errstate(divide="ignore", invalid="ignore"):
        harmonic = np.where(out["w_inv"] > 0, out["w_n"] / out["w_inv"], np.nan)
        timed_mean = np.where(out["w_ss"] > 0, out["w_ssv"] / out["w_ss"], np.nan)
    out["speed_mps"] = np.where(out["kind"].astype(str).str.lower() == "e2", timed_mean, harmonic)
    return out.reindex(columns=det.columns).reset_index(drop=True)

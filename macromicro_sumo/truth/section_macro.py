"""Macro statistics of a section's ground truth: as its detectors estimate them, from the
full trajectories (what the simulation knows), and the hidden count K per snapshot, true
and estimated from the detectors, with the estimate's error.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.data.macro import passage_spacings
from macromicro_sumo.data.section import at_snapshot_times
from macromicro_sumo.road.section import Section, lane_leaders


def station_cells(arcs: np.ndarray, section: Section) -> np.ndarray:
    """Arc length each detector station stands for: the section split half-way between
    stations (around the loop on a closed section)."""
    order = np.argsort(arcs)
    a = arcs[order]
    if len(a) == 1:
        cells = np.array([section.length_m])
    elif section.closed:
        gaps = np.diff(np.concatenate([a, [a[0] + section.length_m]]))
        cells = 0.5 * (gaps + np.roll(gaps, 1))
    else:
        mids = np.concatenate([[0.0], 0.5 * (a[1:] + a[:-1]), [section.length_m]])
        cells = np.diff(mids)
    out = np.empty_like(cells)
    out[order] = cells
    return out


def detector_macro(
    det: pd.DataFrame,
    passages: pd.DataFrame,
    warmup_s: float,
    min_spacing_m: float,
    section: Section,
) -> pd.DataFrame:
    """Macro statistics per run and interval as the section's detectors estimate them.

    Speed: space-mean (E2 weighted by time on the detector; E1 harmonic means weighted by
    counts). Density per lane: E2 vehicles per metre, E1 flow / speed, averaged over the
    detectors. Vehicles on the section: E1 stations' density summed over their lanes and
    integrated along the arc (each station stands for the stretch half-way to its
    neighbours: lane counts that change along the section are weighted right); E2: their
    vehicles scaled to the section's lane length. Spacing spread and speed bounds: from
    the per-vehicle passages.
    """
    spacings = passage_spacings(passages)
    stations = np.sort(det.loc[det["kind"] == "e1", "arc_m"].unique())
    cells = (
        dict(zip(stations, station_cells(stations, section), strict=True)) if len(stations) else {}
    )
    rows = []
    det = det[det["begin_s"] >= warmup_s - 1e-9]
    for (run, begin, end), g in det.groupby(["run", "begin_s", "end_s"], sort=True):
        e1, e2 = g[g["kind"] == "e1"], g[g["kind"] == "e2"]
        if len(e2):
            ss = e2["sampled_seconds_s"].to_numpy()
            v = e2["speed_mps"].to_numpy()
            speed = float(np.nansum(v * ss) / ss.sum()) if ss.sum() > 0 else np.nan
            density = float(np.average(e2["density_vpkm"], weights=e2["length_m"]))
            vehicles = density / 1000.0 * section.lane_length_m
        else:
            n, v = e1["n_veh"].to_numpy(), e1["speed_mps"].to_numpy()
            ok = n > 0
            speed = float(n[ok].sum() / (n[ok] / v[ok]).sum()) if ok.any() else np.nan
            density = float(e1["density_vpkm"].mean())
            per_station = e1.groupby("arc_m")["density_vpkm"].sum()
            vehicles = float(sum(k / 1000.0 * cells[a] for a, k in per_station.items()))
        ip = passages[
            (passages["run"] == run) & (passages["time_s"] >= begin) & (passages["time_s"] < end)
        ]
        sp = spacings[
            (spacings["run"] == run) & (spacings["time_s"] >= begin) & (spacings["time_s"] < end)
        ]
        ps = ip["speed_mps"].to_numpy()
        d = sp["spacing_m"].to_numpy()
        d = d[d >= min_spacing_m * 0.5]  # a lane change between two loops is not a spacing
        rows.append(
            {
                "run": run,
                "begin_s": begin,
                "end_s": end,
                "source": "detectors",
                "mean_speed_mps": speed,
                "std_speed_mps": float(ps.std(ddof=1)) if ps.size > 1 else np.nan,
                "density_vpkm_lane": density,
                "mean_spacing_m": 1000.0 / density if density > 0 else np.nan,
                "std_spacing_m": float(d.std(ddof=1)) if d.size > 1 else np.nan,  # sample std
                "speed_min_mps": float(ps.min()) if ps.size else np.nan,
                "speed_max_mps": float(ps.max()) if ps.size else np.nan,
                "vehicles": vehicles,
            }
        )
    return pd.DataFrame(rows)


def trajectory_macro(
    traj: pd.DataFrame, section: Section, interval_s: float, warmup_s: float, end_s: float
) -> pd.DataFrame:
    """The same statistics from the full trajectories (what the simulation knows)."""
    rows = []
    bounds = np.arange(warmup_s, end_s + 1e-9, interval_s)
    for run, g in traj.groupby("run", sort=True):
        for begin, end in zip(bounds[:-1], bounds[1:], strict=True):
            w = g[(g["time_s"] >= begin) & (g["time_s"] < end)]
            if w.empty:
                continue
            spacing = []
            for _, s in w.groupby("time_s"):
                lead, sp = lane_leaders(
                    s["lane_index"].to_numpy(),
                    s["arc_m"].to_numpy(),
                    section.length_m,
                    section.closed,
                )
                spacing.append(sp[lead >= 0])
            d = np.concatenate(spacing) if spacing else np.array([])
            n_t = w.groupby("time_s").size().mean()
            density = n_t / section.lane_length_m * 1000.0
            rows.append(
                {
                    "run": run,
                    "begin_s": begin,
                    "end_s": end,
                    "source": "trajectories",
                    "mean_speed_mps": float(w["speed_mps"].mean()),
                    "std_speed_mps": float(w["speed_mps"].std(ddof=0)),
                    "density_vpkm_lane": density,
                    "mean_spacing_m": 1000.0 / density if density > 0 else np.nan,
                    "std_spacing_m": float(d.std()) if d.size > 1 else np.nan,
                    "speed_min_mps": float(w["speed_mps"].min()),
                    "speed_max_mps": float(w["speed_mps"].max()),
                    "vehicles": float(n_t),
                }
            )
    return pd.DataFrame(rows)


def k_estimates(
    traj: pd.DataFrame,
    det_macro: pd.DataFrame,
    section: Section,
    every_s: float,
    window_s: float,
) -> pd.DataFrame:
    """Hidden count per snapshot time: the truth, and the estimate from the detectors.

    Estimate: round(vehicles on the section by the detectors) - observed vehicles, the
    detectors' count (see ``detector_macro``) averaged over the intervals centred within ``window_s``
    of the snapshot (``detectors.k_window_s``; at least the interval holding it). Longer
    windows average out platoons that one interval's loops see or miss.
    """
    rows = []
    for (run, t), g in at_snapshot_times(traj, every_s).groupby(["run", "time_s"], sort=True):
        r = det_macro[det_macro["run"] == run]
        centre = 0.5 * (r["begin_s"] + r["end_s"])
        m = r[(centre >= t - window_s / 2) & (centre <= t + window_s / 2)]
        if m.empty:
            m = r[(r["begin_s"] <= t) & (r["end_s"] > t)]
        vehicles = float(m["vehicles"].mean()) if len(m) else np.nan
        if not np.isfinite(vehicles):
            continue
        n_obs = int(g["observed"].sum())
        total = int(round(vehicles))
        k_true = len(g) - n_obs
        k_est = max(0, total - n_obs)
        rows.append(
            {
                "run": run,
                "time_s": t,
                "n_vehicles": len(g),
                "n_observed": n_obs,
                "k_true": k_true,
                "k_est": k_est,
                "k_error": k_est - k_true,
            }
        )
    return pd.DataFrame(
        rows, columns=["run", "time_s", "n_vehicles", "n_observed", "k_true", "k_est", "k_error"]
    )


def k_summary(k_df: pd.DataFrame, section: Section) -> dict[str, float]:
    """The K estimate's error: mean, mean absolute, and mean absolute per lane."""
    if k_df.empty:
        return {"snapshots": 0}
    err = k_df["k_error"].to_numpy(dtype=float)
    lanes = float((section.n_lanes * section.lengths_m).sum() / section.lengths_m.sum())
    return {
        "snapshots": len(err),
        "mean_error_veh": float(err.mean()),
        "mean_abs_error_veh": float(np.abs(err).mean()),
        "mean_abs_error_per_lane_veh": float(np.abs(err).mean() / lanes),
        "mean_k_true": float(k_df["k_true"].mean()),
    }

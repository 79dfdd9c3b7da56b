"""Cleaning a traffic engineer expects before field data feeds the method.

Trajectories: video-extracted positions (NGSIM) carry a few decimetres of noise, which
numerical differentiation turns into metres per second of speed noise and tens of m/s^2
of acceleration noise. Speeds and accelerations are therefore re-derived from the
positions with the symmetric exponential moving average (sEMA) of Thiemann, Treiber and
Kesting (2008), "Estimating acceleration and lane-changing dynamics from Next Generation
Simulation trajectory data", Transportation Research Record 2088, pp. 90-101
(arXiv:0804.0108): positions are smoothed with a kernel exp(-|t_i - t_k| / T), then
differentiated (central differences) and smoothed again; near the ends of a trajectory the
window shrinks symmetrically, as Thiemann et al. do, so a moving vehicle's position does
not lag there. Outliers (|a| beyond a
physical bound, speed jumps no vehicle can make in one sample) and time gaps (a vehicle
missing for more than ``gap_factor`` sampling periods) are flagged; a gap splits the
smoothing, so no kernel reaches across it.

Measured leaders: where a layout gives the spacing to the vehicle's own leader but not the
leader's speed (NGSIM's Space_Headway), the leader's speed is the vehicle's cleaned speed
plus the time derivative of the gap, smoothed as the positions are (sEMA of the spacing
with ``position_width_s``, central differences, sEMA with ``speed_width_s``), within runs
of one leader (a change of leader is a jump in spacing, not a speed).

Stations: intervals with too few samples, with PeMS ``% Observed`` under a threshold
(imputed rather than measured) or without any value are excluded and counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from macromicro_sumo.fielddata.stations import Stations
from macromicro_sumo.fielddata.trajectories import Trajectories
from macromicro_sumo.scenario.data import CLEANING_LAYOUT_DEFAULTS, CleaningConfig

DEFAULT_CLEANING = CleaningConfig()
NGSIM_CLEANING = CleaningConfig(**CLEANING_LAYOUT_DEFAULTS["ngsim"])


def sema(t: np.ndarray, x: np.ndarray, width_s: float) -> np.ndarray:
    """Symmetric exponential moving average of ``x`` sampled at times ``t``: weights
    exp(-|t_i - t_k| / width) over a window symmetric about t_i, cut at 3 widths and, near
    the ends, at the distance to the nearer end (Thiemann et al. 2008): a one-sided window
    there would make a moving vehicle's smoothed position lag by about speed x width."""
    if width_s <= 0 or len(x) < 3:
        return x.astype(float).copy()
    half = np.minimum(3.0 * width_s, np.minimum(t - t[0], t[-1] - t))
    lo = np.searchsorted(t, t - half - 1e-9, side="left")
    hi = np.searchsorted(t, t + half + 1e-9, side="right")
    out = np.empty(len(x))
    for i in range(len(x)):
        w = np.exp(-np.abs(t[lo[i] : hi[i]] - t[i]) / width_s)
        out[i] = (w * x[lo[i] : hi[i]]).sum() / w.sum()
    return out


def segments(t: np.ndarray, gap_factor: float) -> tuple[list[np.ndarray], np.ndarray]:
    """Index runs of one vehicle's samples without a gap, and which samples follow a gap."""
    if len(t) < 2:
        return [np.arange(len(t))], np.zeros(len(t), dtype=bool)
    step = np.diff(t)
    gap = step > gap_factor * np.median(step)
    cuts = np.flatnonzero(gap) + 1
    after = np.zeros(len(t), dtype=bool)
    after[cuts] = True
    return np.split(np.arange(len(t)), cuts), after


# Without leader ids, a spacing that changes faster than this between samples is a new
# leader (a cut-in or a lane change), not a relative speed any pair of vehicles reaches.
LEADER_CHANGE_MPS = 40.0


def leader_runs(t: np.ndarray, leader: np.ndarray, spacing: np.ndarray) -> list[np.ndarray]:
    """Index runs of one vehicle's samples behind one measured leader: same leader id,
    a finite spacing, and no jump of the spacing beyond ``LEADER_CHANGE_MPS``."""
    ok = np.isfinite(spacing)
    cut = np.zeros(len(t), dtype=bool)
    if len(t) > 1:
        rate = np.abs(np.diff(spacing)) / np.maximum(np.diff(t), 1e-9)
        cut[1:] = (leader[1:] != leader[:-1]) | (ok[1:] != ok[:-1]) | ~(rate <= LEADER_CHANGE_MPS)
    starts = np.flatnonzero(cut)
    return [r for r in np.split(np.arange(len(t)), starts) if ok[r[0]]]


def leader_speed_from_gap(
    t: np.ndarray,
    speed_mps: np.ndarray,
    leader: np.ndarray,
    spacing_m: np.ndarray,
    position_width_s: float,
    speed_width_s: float,
) -> np.ndarray:
    """A leader's speed from the measured spacing of one vehicle's samples (in time order):
    own speed + d(spacing)/dt, the spacing smoothed as the cleaning smooths positions (sEMA,
    central differences, sEMA); NaN without a leader or where a run of one leader has a
    single sample. Widths 0: plain central differences."""
    out = np.full(len(t), np.nan)
    for k in leader_runs(t, leader, spacing_m):
        if len(k) < 2:
            continue
        x = sema(t[k], spacing_m[k], position_width_s)
        out[k] = speed_mps[k] + sema(t[k], np.gradient(x, t[k]), speed_width_s)
    return np.maximum(out, 0.0)


@dataclass(frozen=True)
class CleanTrajectories:
    """Cleaned trajectories and the flags of every row (same order as ``frame``)."""

    source: Trajectories
    frame: pd.DataFrame  # trajectories.csv schema, speeds/accelerations re-derived if asked
    raw_speed_mps: np.ndarray  # the file's speeds, row by row with ``frame``
    flags: pd.DataFrame  # accel_outlier, speed_jump, after_gap (bool per row)


def clean_trajectories(
    traj: Trajectories, cfg: CleaningConfig = DEFAULT_CLEANING
) -> CleanTrajectories:
    """Flag outliers and gaps; with ``cfg.smoother = "ema"`` re-derive speeds and
    accelerations from the positions (the lane and the vehicle's rows are kept)."""
    df = traj.frame.sort_values(["vehicle_id", "time_s"], kind="stable").reset_index(drop=True)
    t = df["time_s"].to_numpy()
    arc = df["arc_m"].to_numpy()
    raw_v = df["speed_mps"].to_numpy().copy()
    raw_a = df["accel_mps2"].to_numpy().copy()
    v, a = raw_v.copy(), raw_a.copy()
    jump = np.zeros(len(df), dtype=bool)
    after_gap = np.zeros(len(df), dtype=bool)
    for idx in df.groupby("vehicle_id", sort=False).indices.values():
        runs, after = segments(t[idx], cfg.gap_factor)
        after_gap[idx] = after
        for seg in runs:
            k = idx[seg]
            if len(k) < 2:
                continue
            dt = np.diff(t[k])
            # A speed change no vehicle makes in one sample (twice the physical bound).
            jump[k[1:]] = np.abs(np.diff(raw_v[k])) > 2.0 * cfg.max_accel_mps2 * dt
            if cfg.smoother == "ema":
                x = sema(t[k], arc[k], cfg.position_width_s)
                v[k] = np.maximum(sema(t[k], np.gradient(x, t[k]), cfg.speed_width_s), 0.0)
                a[k] = sema(t[k], np.gradient(v[k], t[k]), cfg.accel_width_s)
    frame = df.assign(speed_mps=v, accel_mps2=a)
    if traj.leader_measured:
        frame = frame.assign(leader_speed_mps=_leader_speeds(frame, cfg))
    flags = pd.DataFrame(
        {
            "vehicle_id": df["vehicle_id"].to_numpy(),
            "time_s": t,
            # The file's own or the re-derived acceleration beyond the physical bound.
            "accel_outlier": np.maximum(np.abs(a), np.abs(raw_a)) > cfg.max_accel_mps2,
            "speed_jump": jump,
            "after_gap": after_gap,
        }
    )
    return CleanTrajectories(traj, frame, raw_v, flags)


def _leader_speeds(frame: pd.DataFrame, cfg: CleaningConfig) -> np.ndarray:
    """The measured leader speeds, derived from the gap where the file gives none."""
    lead_v = frame["leader_speed_mps"].to_numpy(dtype=float).copy()
    need = np.isnan(lead_v) & np.isfinite(frame["leader_spacing_m"].to_numpy(dtype=float))
    if not need.any():
        return lead_v
    ema = cfg.smoother == "ema"
    t, v = frame["time_s"].to_numpy(), frame["speed_mps"].to_numpy()
    leader = frame["leader_id"].astype(str).to_numpy()
    spacing = frame["leader_spacing_m"].to_numpy(dtype=float)
    for idx in frame.groupby("vehicle_id", sort=False).indices.values():
        if not need[idx].any():
            continue
        for seg in segments(t[idx], cfg.gap_factor)[0]:  # no derivative across a time gap
            k = idx[seg]
            derived = leader_speed_from_gap(
                t[k],
                v[k],
                leader[k],
                spacing[k],
                cfg.position_width_s if ema else 0.0,
                cfg.speed_width_s if ema else 0.0,
            )
            lead_v[k] = np.where(need[k], derived, lead_v[k])
    return lead_v


@dataclass(frozen=True)
class CleanStations:
    """Kept station intervals and the reason each dropped one was excluded."""

    source: Stations
    frame: pd.DataFrame  # detectors.csv schema, kept rows only
    dropped: pd.DataFrame  # detector_id, lane_index, begin_s, reason


def clean_stations(st: Stations, cfg: CleaningConfig = DEFAULT_CLEANING) -> CleanStations:
    """Exclude intervals with too few samples, too little observed (PeMS), or no value."""
    f, q = st.frame.reset_index(drop=True), st.quality.reset_index(drop=True)
    reason = np.full(len(f), "", dtype=object)
    no_value = f["n_veh"].isna() & f["speed_mps"].isna() & f["occupancy_pct"].isna()
    reason[no_value.to_numpy()] = "no value"
    few = (q["samples"] < cfg.min_samples).to_numpy() & (reason == "")
    reason[few] = f"samples < {cfg.min_samples:g}"
    low = (q["observed_pct"] < cfg.min_observed_pct).to_numpy() & (reason == "")
    reason[low] = f"observed < {cfg.min_observed_pct:g} %"
    drop = reason != ""
    dropped = f.loc[drop, ["detector_id", "lane_index", "begin_s"]].assign(reason=reason[drop])
    return CleanStations(st, f[~drop].reset_index(drop=True), dropped.reset_index(drop=True))

"""Microscopic distributions of a deployment against the ground truth, from trajectories.csv:
speed, acceleration, time headway and time-to-collision, compared by their Wasserstein-1
distance.

``trajectories.csv`` has ``lane_index`` and ``arc_m``: leaders are found here, per lane, with
``road.leaders.lane_leaders``. Every function is pure.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd

from macromicro_sumo.evaluation.statistics import w1
from macromicro_sumo.road.leaders import lane_leaders, section_leaders
from macromicro_sumo.road.section import Section

# Below this speed a time headway gap / speed is dominated by the division (a queued
# vehicle 2 m behind its leader at 0.01 m/s would have a 200 s headway).
HEADWAY_MIN_SPEED_MPS = 0.5
# Time-to-collision is kept up to this value: beyond it nobody is on a collision course
# within any horizon that matters for safety (surrogate safety studies flag 1.5-3 s), and
# unbounded values (closing at 1 mm/s) would dominate a distance between distributions.
TTC_MAX_S = 30.0
DEFAULT_VEHICLE_LENGTH_M = 5.0  # SUMO's default passenger length, for unknown vTypes

LANE_COLUMNS = (
    "run",
    "time_s",
    "vehicle_id",
    "lane_index",
    "arc_m",
    "speed_mps",
    "accel_mps2",
    "gap_m",
    "leader_speed_mps",
)
DISTRIBUTIONS = ("speed_mps", "accel_mps2", "headway_s", "ttc_s")


def time_headways(
    gap_m: np.ndarray, speed_mps: np.ndarray, min_speed_mps: float = HEADWAY_MIN_SPEED_MPS
) -> np.ndarray:
    """Time headway [s] = bumper-to-bumper gap / own speed, of vehicles faster than
    ``min_speed_mps`` that have a leader (finite gap)."""
    gap, v = np.asarray(gap_m, dtype=float), np.asarray(speed_mps, dtype=float)
    ok = np.isfinite(gap) & (v > min_speed_mps)
    return gap[ok] / v[ok]


def times_to_collision(
    gap_m: np.ndarray,
    speed_mps: np.ndarray,
    leader_speed_mps: np.ndarray,
    max_s: float = TTC_MAX_S,
) -> np.ndarray:
    """Time-to-collision [s] = gap / closing speed (own speed - leader's speed), of
    vehicles closing in on a leader (closing speed > 0), up to ``max_s``."""
    gap = np.asarray(gap_m, dtype=float)
    closing = np.asarray(speed_mps, dtype=float) - np.asarray(leader_speed_mps, dtype=float)
    ok = np.isfinite(gap) & np.isfinite(closing) & (closing > 0)
    ttc = np.maximum(gap[ok], 0.0) / closing[ok]
    return ttc[ttc <= max_s]


def lane_trajectories(
    traj: pd.DataFrame,
    section: Section | None = None,
    vehicle_lengths_m: Mapping[str, float] | None = None,
    leaders: bool = True,
) -> pd.DataFrame:
    """Rows of ``trajectories.csv`` in one schema (``LANE_COLUMNS``), with the gap to the
    vehicle ahead and that vehicle's speed (NaN: none on the section).

    Rows get their leader here, per run and time: along the ``section``'s lane connections (``section_leaders``: where a
    lane is added on the right, the leader is the physically next vehicle, not the one
    with the same lane index), by lane index on an open road without ``section``. A lane's
    end is not a vehicle: no leader there. Gap = spacing - the leader's length (its vType's,
    from ``vehicle_lengths_m``, else ``DEFAULT_VEHICLE_LENGTH_M``). Deploy outputs that
    record ``gap_m`` and ``leader_speed_mps`` themselves are taken as they are. Without
    ``leaders`` (plots need none) section rows keep NaN gaps.
    """
    out = traj.reindex(columns=[*LANE_COLUMNS, "vtype"]).reset_index(drop=True)
    if traj.columns.isin(["gap_m", "leader_speed_mps"]).sum() == 2 or not leaders:
        return out[list(LANE_COLUMNS)]
    lane = out["lane_index"].to_numpy(dtype=np.int64)
    arc = out["arc_m"].to_numpy(dtype=float)
    snap = pd.MultiIndex.from_frame(out[["run", "time_s"]]).factorize()[0].astype(np.int64)
    leader, spacing = snapshot_leaders(snap, lane, arc, section)
    has = leader >= 0
    lengths = out["vtype"].map(dict(vehicle_lengths_m or {})).fillna(DEFAULT_VEHICLE_LENGTH_M)
    lead_len = lengths.to_numpy(dtype=float)[np.where(has, leader, 0)]
    speed = out["speed_mps"].to_numpy(dtype=float)
    out["gap_m"] = np.where(has, spacing - lead_len, np.nan)
    out["leader_speed_mps"] = np.where(has, speed[np.where(has, leader, 0)], np.nan)
    return out[list(LANE_COLUMNS)]


def snapshot_leaders(
    snap: np.ndarray, lane: np.ndarray, arc_m: np.ndarray, section: Section | None
) -> tuple[np.ndarray, np.ndarray]:
    """Leader (row index, -1: none or a lane's end) and spacing of every row, within its
    snapshot ``snap``."""
    if section is None:
        # One lane_leaders call for all snapshots: the (snapshot, lane) key as the lane,
        # so leaders are only ever looked for within a single snapshot.
        key = snap * (int(lane.max(initial=0)) + 1) + lane
        return lane_leaders(key, arc_m, 0.0, False)
    leader = np.full(len(snap), -1, dtype=np.int64)
    spacing = np.full(len(snap), np.nan)
    order = np.argsort(snap, kind="stable")
    cuts = np.flatnonzero(np.diff(snap[order])) + 1
    for rows in np.split(order, cuts):
        lead, sp = section_leaders(section, lane[rows], arc_m[rows])
        vehicle = lead >= 0
        leader[rows[vehicle]] = rows[lead[vehicle]]
        spacing[rows] = sp
    return leader, spacing


def same_window(truth: pd.DataFrame, method: pd.DataFrame) -> pd.DataFrame:
    """The truth's rows of the runs ``method`` has, up to the last time ``method`` recorded
    in that run (a deployment may record only its first minutes)."""
    last = method.groupby("run")["time_s"].max()
    end = truth["run"].map(last)
    return truth[end.notna() & (truth["time_s"] <= end + 1e-9)]


def samples(lanes: pd.DataFrame) -> dict[str, np.ndarray]:
    """The four samples compared, from rows in ``lane_trajectories``' schema."""
    gap, v = lanes["gap_m"].to_numpy(dtype=float), lanes["speed_mps"].to_numpy(dtype=float)
    return {
        "speed_mps": v,
        "accel_mps2": lanes["accel_mps2"].to_numpy(dtype=float),
        "headway_s": time_headways(gap, v),
        "ttc_s": times_to_collision(gap, v, lanes["leader_speed_mps"].to_numpy(dtype=float)),
    }


def distribution_distances(truth: pd.DataFrame, method: pd.DataFrame) -> dict[str, float]:
    """W1 distances ``w1_<sample>`` between the truth's and the method's samples, both in
    ``lane_trajectories``' schema, over the runs and time window the method recorded."""
    method = method[method["run"].isin(truth["run"].unique())]
    a, b = samples(same_window(truth, method)), samples(method)
    return {f"w1_{name}": w1(a[name], b[name]) for name in DISTRIBUTIONS}

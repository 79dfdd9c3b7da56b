"""Micro pairs behind the leader a vehicle measured, not the next vehicle recorded.

Field trajectories hold the instrumented (observed) vehicles only. Their leaders found
among the recorded vehicles are the next *observed* vehicle, with hidden ones possibly in
between: an IDM fitted to those pairs is another driver (docs/field-data.md). The
instrumented vehicles measure their own leader (radar; NGSIM ``Preceding`` /
``Space_Headway``, highD ``precedingId`` / ``dhw`` / ``precedingXVelocity``), which the
readers keep as ``LEADER_COLUMNS`` (``measured_leaders``: units, "no leader", a bumper gap
made a spacing); ``with_measured_leaders`` puts it into the observations.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.fielddata.schema import LEADER_COLUMNS, MAX_SPEED_MPS, check_range
from macromicro_sumo.road.leaders import bumper_gap_m
from macromicro_sumo.road.physics import LEADER_COLUMN, OBSERVATION_FEATURES, observes_gap
from macromicro_sumo.road.section import NO_LEADER_GAP_M

# A measured spacing beyond this is no radar's range but a unit declared wrong.
MAX_LEADER_SPACING_M = 1000.0


def measured_leaders(
    raw: pd.DataFrame,
    vid: np.ndarray,
    speed_mps: np.ndarray,
    lu: float,
    su: float,
    path: Path,
    cols: dict[str, str],
    rows: np.ndarray,
    lines: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(leader_id, spacing [m], leader speed [m/s]) of each row from the raw table's
    ``lead_id``, ``lead_spacing`` (front to front) or ``lead_gap`` (bumper to bumper: the
    leader's length is added, its median length in the file, else the file's median
    length), ``lead_speed`` or ``lead_dv`` (own minus leader), in file units; None where the
    layout has no spacing. A leader id 0 / empty or a spacing 0 / empty is no leader (NGSIM
    and highD write 0 there): "" and NaN; a negative spacing is a one-line error. A leader
    speed not given is NaN here and derived from the gap by the cleaning
    (``cleaning.leader_speed_from_gap``)."""
    if "lead_spacing" not in raw.columns and "lead_gap" not in raw.columns:
        return None
    ids = raw["lead_id"].astype(str).str.strip() if "lead_id" in raw.columns else None
    if "lead_spacing" in raw.columns:
        spacing = raw["lead_spacing"].to_numpy(dtype=float) * lu
        column = cols.get("lead_spacing", "spacing")
    else:
        length = raw["length"].to_numpy(dtype=float) * lu
        own = pd.Series(length).groupby(vid).median()
        fallback = float(np.nanmedian(length)) if np.isfinite(length).any() else np.nan
        lead_len = (
            ids.map(own).to_numpy(dtype=float) if ids is not None else np.full(len(raw), np.nan)
        )
        spacing = raw["lead_gap"].to_numpy(dtype=float) * lu
        spacing = spacing + np.where(np.isfinite(lead_len), lead_len, fallback)
        column = cols.get("lead_gap", "gap")
    # 0 or empty is the layouts' "nothing ahead"; a negative one is refused below.
    measured = raw["lead_spacing" if "lead_spacing" in raw.columns else "lead_gap"]
    none = np.nan_to_num(measured.to_numpy(dtype=float)) == 0.0
    if ids is not None:
        none |= ids.isin(["", "0", "0.0", "nan", "None"]).to_numpy()
    spacing = np.where(none, np.nan, spacing)
    check_range(
        spacing,
        0.0,
        MAX_LEADER_SPACING_M,
        path,
        column,
        "leader spacing [m]",
        "is length_unit right?",
        rows,
        lines,
    )
    if "lead_speed" in raw.columns:
        lead_v = raw["lead_speed"].to_numpy(dtype=float) * su
    elif "lead_dv" in raw.columns:
        lead_v = speed_mps - raw["lead_dv"].to_numpy(dtype=float) * su
    else:
        lead_v = np.full(len(raw), np.nan)
    lead_v = np.where(none, np.nan, lead_v)
    check_range(
        lead_v,
        0.0,
        MAX_SPEED_MPS,
        path,
        cols.get("lead_speed", "leader speed"),
        "leader speed [m/s]",
        "is speed_unit right?",
        rows,
        lines,
    )
    leader = np.where(none, "", ids.to_numpy() if ids is not None else "?")
    return leader.astype(object), spacing, lead_v


def id_strings(ids: pd.Series) -> np.ndarray:
    """Vehicle ids as text; a numeric column with empty cells (read as floats) as whole
    numbers, so "12.0" names vehicle 12; empty: ""."""
    num = pd.to_numeric(ids, errors="coerce")
    if num.notna().any() and (num.isna() == ids.isna()).all() and (num.dropna() % 1 == 0).all():
        return num.astype("Int64").astype(str).replace("<NA>", "").to_numpy()
    return ids.fillna("").astype(str).to_numpy()


def has_measured_leaders(frame: pd.DataFrame) -> bool:
    """Whether trajectory rows carry the vehicles' own leader measurement."""
    return all(c in frame.columns for c in LEADER_COLUMNS[1:])


def with_measured_leaders(
    obs: np.ndarray,
    leader: np.ndarray,
    frame: pd.DataFrame,
    observation: str,
    lengths: pd.Series | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Observations ``obs`` (rows of ``frame``, one scene) with each row's measured leader
    where it is nearer than the leader found among the recorded vehicles (``leader`` -1:
    none found): spacing = the measured one, delta_v = own speed - the measured leader's.
    The recorded vehicles are a subset of the road's, so the true leader is never farther
    than a recorded one; a lane's end found nearer (``leader`` STOP) stays, and a leader
    ``NO_LEADER_GAP_M`` or farther is none (``section_observations``' look-ahead). Rows
    without a measurement (NaN) keep the recorded scene's leader. A gap layout
    (``physics.observes_gap``) observes the measured spacing less the leader's length
    (``measured_leader_length_m``: ``lengths``, each recorded vehicle's length by id).
    Returns (observations, replaced)."""
    spacing = frame["leader_spacing_m"].to_numpy(dtype=float)
    lead_v = frame["leader_speed_mps"].to_numpy(dtype=float)
    seen = spacing
    if observes_gap(observation):  # compared and written as the gap it observes
        seen = bumper_gap_m(spacing, measured_leader_length_m(frame, lengths))
    ok = np.isfinite(spacing) & np.isfinite(lead_v) & np.isfinite(seen)
    with np.errstate(invalid="ignore"):  # one as far as NO_LEADER_GAP_M: none, as observed
        use = ok & (spacing < NO_LEADER_GAP_M) & ((leader == -1) | (seen < obs[:, LEADER_COLUMN]))
    out = obs.copy()
    out[use, LEADER_COLUMN] = seen[use]
    out[use, OBSERVATION_FEATURES[observation].index("delta_v_mps")] = (
        frame["speed_mps"].to_numpy(dtype=float)[use] - lead_v[use]
    )
    return out, use


def measured_leader_length_m(frame: pd.DataFrame, lengths: pd.Series | None) -> np.ndarray:
    """Each row's measured leader's length [m]: the leader's own (``lengths``: each recorded
    vehicle's length, indexed by vehicle id; the leader's ``leader_id`` among them), else
    the median of ``lengths`` (the recorded vehicles', as ``measured_leaders`` takes for a
    bumper gap's leader it cannot find: the data's typical vehicle), else NaN (no length
    known: that row keeps the recorded scene's leader)."""
    n = len(frame)
    if lengths is None or not lengths.notna().any():
        return np.full(n, np.nan)
    fallback = float(lengths.median())
    if "leader_id" not in frame:
        return np.full(n, fallback)
    own = frame["leader_id"].astype(str).map(lengths.groupby(lengths.index.astype(str)).first())
    return own.fillna(fallback).to_numpy(dtype=float)

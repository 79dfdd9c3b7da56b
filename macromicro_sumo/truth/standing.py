"""The standing queue at a fixed-time signal as point loops see it: the room a standing
vehicle takes (``jam_spacing_m``) and the density a loop near the stop line misses while a
queue stands over it (``standing_density``).

A point loop counts the vehicles that pass it; its interval density is their flow over their
speed, the moving vehicles' share. A vehicle standing over it during the red passes only at
the green (about 6 m/s from a loop within 25 m of the line), so that density leaves out the
red's standing queue. SUMO's equal cars (5 m, 2.5 m gap) also stand with their gap over a
loop 15 m from the line, so its occupancy misses them too. Measured from 240 s on the
untuned arterials 801-820 with point loops, per lane: the stop bar read 36 against 63
veh/km within 20 m, the 15 m loop 40 against 88 (docs/sections-log.md, stop 45, hK45).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.road.leaders import STANDING_MIN_GAP_M
from macromicro_sumo.truth.density import DEFAULT_VEHICLE_LENGTH_M, effective_length_m
from macromicro_sumo.truth.section_macro import loop_lengths_m

NEAR_LINE_M = 25.0
"""A station at most this far before its stop line (the stop bar, the tool's 15 m station)
reads the green's discharge, not the red's standing queue."""


NEAR_LINE_ALL_SHARE = 0.5
"""``signal_counts.approach_count(near_line="all")``: the share of ``standing_density``
added to the near-line stations of every approach. On ground truths without SUMO's
standing lattice (``truth.vtype_spread``) the near-line loops still read low (spread 802,
per lane: the stop bar 27 against 68 veh/km, the 15 m loop 42 against 98), and the whole
of it overshoots (stop 48, hH48, from 240 s, K per lane free / congested: 801-812, 1161,
1407 3.76 / 4.10, bias -3.30 / -3.41 -> bias +1.93 / +1.96). Half, set on those: 2.59 /
2.90; on the held-out 813-820 3.52 / 3.98 -> 2.10 / 2.49 (bias -0.47 / -0.52)."""


def jam_spacing_m(det: pd.DataFrame) -> float:
    """Room a vehicle takes in a standing queue: the median over the loops of their
    effective vehicle length (``density.effective_length_m``, from their free-flowing
    intervals; SUMO's passenger car where none flowed) plus the gap between standing
    vehicles, SUMO's default minGap (``road.leaders.STANDING_MIN_GAP_M``)."""
    cols = ["flow_vph", "speed_mps", "occupancy_pct"]
    e1 = det[det["kind"] == "e1"]
    loop = pd.Series(loop_lengths_m(e1), index=e1.index)
    # Less the occupancy loop's own length (dual loops), which the calibration holds.
    lengths = [
        effective_length_m(*(g[c].to_numpy(dtype=float) for c in cols), np.nan)
        - float(loop[g.index].max())
        for _, g in e1.groupby("detector_id")
    ]
    ok = [x for x in lengths if np.isfinite(x)]
    return float(np.median(ok) if ok else DEFAULT_VEHICLE_LENGTH_M) + STANDING_MIN_GAP_M


def standing_seconds(
    to_line_m: np.ndarray,
    flow_per_lane: float,
    red_s: float,
    spacing_m: float,
    v_free_mps: float,
    wave_mps: float,
) -> np.ndarray:
    """Seconds a queue stands over each point ``to_line_m`` before the line in one cycle:
    from when its back, growing at ``w`` from the start of the red (Lighthill-Whitham: the
    arrival flow over the jam density less the arrivals'; an approach that cleared at the
    green before), reaches the point, to when the start of green, running back at
    ``wave_mps``, leaves it."""
    w = flow_per_lane / max(1.0 / spacing_m - flow_per_lane / v_free_mps, 1e-6)
    if w <= 0.0:
        return np.zeros(len(to_line_m))
    x = np.asarray(to_line_m, dtype=float)
    return np.clip(red_s + x / wave_mps - x / w, 0.0, red_s + x / wave_mps)


def standing_density(
    to_line_m: np.ndarray,
    reds: list[tuple[float, float]],
    span_s: float,
    lanes: int,
    spacing_m: float,
    v_free_mps: float,
    wave_mps: float,
) -> np.ndarray:
    """Density over ``lanes`` (veh/km) that a queue standing at jam spacing adds at each
    point ``to_line_m`` (0 beyond ``NEAR_LINE_M``) over an interval of ``span_s``: its
    ``standing_seconds`` per red of ``reds`` (vehicles arriving at the line during the red,
    the red's seconds) over the interval."""
    x = np.asarray(to_line_m, dtype=float)
    stand = np.zeros(len(x))
    for arrived, red in reds:
        if red > 0.0:
            flow = max(arrived, 0.0) / lanes / red
            stand += standing_seconds(x, flow, red, spacing_m, v_free_mps, wave_mps)
    near = (x >= 0.0) & (x <= NEAR_LINE_M)
    return np.where(near, stand / span_s * lanes * 1000.0 / spacing_m, 0.0)

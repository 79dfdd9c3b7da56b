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


NEAR_LINE_STATION_SHARE = 1.0
"""``signal_counts.approach_count(near_line="station")``: the share of ``standing_density``
added to a near-line station that saw none of it (``seen_share``). Set on spread 801-812,
1161, 1407 from 240 s (stop 49, hH49; K per lane free / congested, "all" 2.59 / 2.90): 1.0
2.38 / 2.67 (bias -0.27 / -0.20), 0.7 2.62 / 2.94, 1.3 2.61 / 2.78. Held out, spread
813-820: 2.10 / 2.49 -> 2.09 / 2.43; plain (lattice) 813-820 2.47 / 2.70 -> 1.88 / 2.30."""

SEEN_RATIO = (0.4, 1.0)
"""A near-line loop's interval occupancy over the share of the interval a queue stands over
it (``standing_density``'s): at or below the first it missed the standing queue (a loop in
front of the first car or in a gap: the passing vehicles alone occupy it that much), at or
above the second a car stood over it and its density has the queue. Spread 801-812, 1161,
1407 from 240 s (stop 49, hH49), the near-line loops' read density against the true one
within 7.5 m, per lane: 0.2-0.4 read 31 against 95 (the model's queue 56); 0.8-1.0 74
against 96; 1.0-1.5 98 against 94."""


def seen_share(
    occupancy_pct: np.ndarray, added_vpkm: np.ndarray, lanes: int, spacing_m: float
) -> np.ndarray:
    """Per near-line station, the share of its ``standing_density`` (``added_vpkm``, over
    ``lanes``) its loops missed: 1 where their occupancy (``occupancy_pct``, the mean over
    its lanes) is at most ``SEEN_RATIO[0]`` of the seconds the queue stands over it (the
    added density at jam spacing ``spacing_m``), 0 from ``SEEN_RATIO[1]`` on, linear
    between; 1 where no occupancy was reported."""
    stand = np.asarray(added_vpkm, dtype=float) / lanes * spacing_m / 1000.0 * 100.0
    occ = np.asarray(occupancy_pct, dtype=float)
    lo, hi = SEEN_RATIO
    ratio = np.divide(occ, stand, out=np.zeros(len(occ)), where=stand > 0)
    missed = np.clip((hi - ratio) / (hi - lo), 0.0, 1.0)
    return np.where(np.isfinite(occ), missed, 1.0)


def near_line_share(near_line: bool | str) -> tuple[float, bool] | None:
    """``signal_counts.approach_count``'s ``near_line`` as (the share of the near-line
    standing queue every approach's density constant takes, whether each station's
    ``seen_share`` scales it): "all" ``NEAR_LINE_ALL_SHARE``, "station"
    ``NEAR_LINE_STATION_SHARE`` by station; None for the others (no share on every
    approach)."""
    if near_line == "all":
        return NEAR_LINE_ALL_SHARE, False
    if near_line == "station":
        return NEAR_LINE_STATION_SHARE, True
    return None


def near_line_profile(
    k: pd.Series,
    e1: pd.DataFrame,
    line_m: float,
    up_m: float,
    queue: tuple,
    share: float,
    by_station: bool,
) -> pd.Series:
    """The stations' densities ``k`` (veh/km over the lanes by arc, one interval's, ``e1``
    its rows) on an approach from ``up_m`` to the stop line at ``line_m``, with ``share`` of
    the standing queue added past ``up_m`` (``standing_density`` of ``queue``: reds, the
    interval's seconds, lanes, jam spacing, free and wave speed). ``by_station``: each
    near-line station's times its ``seen_share``."""
    reds, span_s, lanes, spacing_m, v_free, wave = queue
    arcs = k.index.to_numpy(dtype=float)
    stand = standing_density(line_m - arcs, reds, span_s, lanes, spacing_m, v_free, wave)
    if by_station:
        occ = e1.groupby("arc_m")["occupancy_pct"].mean().reindex(k.index).to_numpy(dtype=float)
        stand = stand * seen_share(occ, stand, lanes, spacing_m)
    return k + np.where(arcs > up_m, share * stand, 0.0)


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

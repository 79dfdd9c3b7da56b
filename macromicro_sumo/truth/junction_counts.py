"""A signalised junction stretch's vehicles (from the stop bar through the junction to the
first station past it) from the stop bar's interval counts timed by the signal's program:
a diagnostic (``scripts/bench_signal_approaches.py --junction-counts``), not a part of K.

A junction stretch holds the vehicles that crossed its stop bar within the time they take
to cross it: many during green (the stop bar discharges at saturation), none a crossing
time after the end of green. The interval density estimate (90 s, a whole cycle) holds the
cycle's mean at every snapshot; the counts follow the cycle (``signal_counts.arrivals``:
the station past the junction's count spread over the line's passing seconds, the
vehicles that turn in from the side streets over its stopping seconds). Where that station
stands in a queue the density estimate is kept (``signal_counts.queued_share``).

Why not in K (docs/sections-log.md, stop 45): the approach past the junction already
counts these vehicles, its arrivals being timed at the previous stop bar; the junction's
interval density in the rest is a double count of their mean that the approach's
constant, set on the density estimate, takes out. Added to K as it stands, the count
doubles them within the cycle: arterials 801-820 from 240 s, dual loops, 2.53 / 2.71 ->
2.42 / 3.39 vehicles per lane free / congested. Made consistent (the approach's arrivals a
crossing later) it gives 2.17 / 2.78 and is mixed on the drawn scenarios' arterials.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.section_macro import (
    cut_at_lines,
    integrate_stations,
    loop_lengths_m,
    station_density,
)
from macromicro_sumo.truth.signal_counts import (
    AFTER_LINE_M,
    STOP_BAR_REACH_M,
    Approach,
    arrivals,
    queued_share,
    station_counts,
)
from macromicro_sumo.truth.signal_lines import StopLine
from macromicro_sumo.truth.stations import Piece, full_stations, station_speeds


def junction_stretches(
    det: pd.DataFrame, section: Section, lines: list[StopLine]
) -> list[Approach]:
    """Each stop line's junction stretch as an ``Approach`` from its stop bar (``up_m``,
    within ``STOP_BAR_REACH_M`` before the line) to the first station that counts every
    lane past the line (``bar_m``, at most ``AFTER_LINE_M`` past it), ``before`` the stop
    bar and its line (the stretch's arrivals are the stop bar's, timed by the program)."""
    arcs = full_stations(det, section)
    out = []
    for line in lines:
        bars = arcs[(arcs <= line.arc_m) & (arcs >= line.arc_m - STOP_BAR_REACH_M)]
        past = arcs[(arcs > line.arc_m) & (arcs <= line.arc_m + AFTER_LINE_M)]
        if len(bars) and len(past):
            bar = float(bars[-1])
            out.append(Approach(bar, float(past[0]), line, (bar, line)))
    return out


def interval_speeds(det: pd.DataFrame, arc: float) -> np.ndarray:
    """A station's interval speeds over its lanes (``stations.station_speeds``), in the order
    of its intervals."""
    e1 = det[(det["arc_m"] == arc) & (det["kind"] == "e1")]
    return np.array([float(station_speeds(g).iloc[0]) for _, g in e1.groupby("begin_s", sort=True)])


def junction_count(
    det: pd.DataFrame, j: Approach, at_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(vehicles on the junction stretch ``j`` at ``at_s``: those that arrived at the station
    past it, timed by the program (``signal_counts.arrivals``), within the time they take
    to cross the stretch at the harmonic mean of its two stations' interval speeds; per
    time the weight of the density estimate instead, the station past it's
    ``queued_share``)."""
    past = Approach(j.bar_m, j.bar_m, j.line, j.before)  # arrivals counted at the far station
    v = np.vstack([interval_speeds(det, j.up_m), interval_speeds(det, j.bar_m)])
    ok = (v > 0).all(axis=0)
    harmonic = np.where(ok, 2.0 / (1.0 / np.where(ok, v, 1.0)).sum(axis=0), np.nan)
    begin = station_counts(det, j.bar_m)[0]
    at = np.asarray(at_s, dtype=float)
    k = np.clip(np.searchsorted(begin, at, side="right") - 1, 0, len(begin) - 1)
    w = np.where(np.isfinite(harmonic[k]), queued_share(det, j.bar_m)[k], 1.0)
    travel = (j.bar_m - j.up_m) / np.where(np.isfinite(harmonic[k]), harmonic[k], 1.0)
    return np.maximum(arrivals(det, past, at) - arrivals(det, past, at - travel), 0.0), w


def junction_pieces(
    det: pd.DataFrame,
    section: Section,
    lines: list[StopLine],
    run: int,
    at_s: np.ndarray,
    rest: pd.DataFrame,
) -> tuple[dict[str, Piece], pd.DataFrame]:
    """The junction stretches counted at ``at_s`` (``junction_count``, blended with their
    density estimate by its weight) as one piece, ``junctions``, and ``rest`` (per interval
    ``begin_s, end_s, vehicles``, ``signal_counts.approach_pieces``') less their density
    estimate (the difference: what the rest holds on them)."""
    d = det[det["run"] == run]
    stretches = junction_stretches(d, section, lines)
    if not stretches:
        return {}, rest
    at = np.asarray(at_s, dtype=float)
    cut = [line.arc_m for line in lines] if (loop_lengths_m(d) > 0).any() else []
    dens, bounds = [], []
    for (begin, _), e1 in d[d["kind"] == "e1"].groupby(["begin_s", "end_s"], sort=True):
        per_station = cut_at_lines(station_density(e1, section), cut)
        dens.append([integrate_stations(per_station, section, j.up_m, j.bar_m) for j in stretches])
        bounds.append(begin)
    dens_arr = np.array(dens)  # (intervals, stretches)
    k = np.clip(np.searchsorted(np.array(bounds), at, side="right") - 1, 0, len(bounds) - 1)
    counted = np.zeros(len(at))
    for i, j in enumerate(stretches):
        n, w = junction_count(d, j, at)
        counted += (1.0 - w) * n + w * dens_arr[k, i]
    less = pd.Series(dens_arr.sum(axis=1), index=np.array(bounds))
    rest = rest.assign(vehicles=rest["vehicles"] - less.reindex(rest["begin_s"]).to_numpy())
    return {"junctions": Piece(tuple((j.up_m, j.bar_m) for j in stretches), counted)}, rest

"""The hidden count on signal approaches from the stations' interval counts (field data) and
the signals' fixed-time programs (the net file's ``tlLogic``; field users have them too).

An approach runs from the first station that counts every lane past the previous junction
(or the section's entry) to the stop-bar station just before the stop line
(``STOP_BAR_REACH_M``). Nothing enters or leaves it between them, so its count is a
constant plus the vehicles in at the upstream station less those out at the stop bar, known
exactly at the intervals' bounds. Within an interval the stop bar's count is spread over the
seconds its signal lets the section's lanes pass (G, g or y). The upstream station's: past
a signal (``AFTER_LINE_M``) the previous stop bar's count over that signal's passing
seconds and the rest (side streets turning in) over its stopping ones; at the entry evenly,
or, where the station stands in the queue (``QUEUED_MPS``), over its own line's passing
seconds as late as the start of green takes to run back to it (``WAVE_MPS``). The stop lines
and their programs: ``signal_lines``.

The constant: the one that puts the approach on its density estimate on average over the record
(``density_constant``), raised where that leaves fewer vehicles than the lower bounds: at the
intervals' bounds (where the counts are exact) the count is at least the vehicles that crossed
the upstream station within the free travel time over the approach (they cannot have reached the
line; ``CLEAR_QUANTILE`` of these) and at least 0, and at the starts of green where a queue
stands (a station's interval speed at or below ``QUEUE_REACH_MPS``) at least the queue that
reaches back to it at jam spacing (``queue_floor``, ``queue_constant``; the density estimate of
a queue reads its loops, which a standing queue's gaps can leave empty: from 240 s on, arterials
1, 2, 600-603 in congestion 3.95 -> 2.92 vehicles per lane). A record starts mid-traffic in the
field: the lower bounds alone, whose largest was taken until stop 39, held only where the record
started from an empty road (a simulation's start): from 240 s on, arterials 1, 2, 600-603 were
11.19 / 14.82 vehicles per lane, free / congested. The constant must leave the count below the
approach's room (lane-metres over ``density.JAM_SPACING_M``) at every interval bound, else the
counts drift (a loop that misses or double-counts) and the approach keeps the density estimate.
The stretch past the last signal is the vehicles that crossed its first station within the
travel time at its stations' interval speed (``free_count``; its density estimate where they
stand). The rest of the section (the junctions, the end pieces) keeps the density estimate. The
programs' clock is taken as the data's (a simulation's: SUMO's).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from macromicro_sumo.road.section import Section
from macromicro_sumo.truth import standing
from macromicro_sumo.truth.density import JAM_SPACING_M, occupancy_weight, rising_integral
from macromicro_sumo.truth.section_macro import (
    cut_at_lines,
    edie_densities,
    integrate_stations,
    loop_lengths_m,
    station_density,
)
from macromicro_sumo.truth.signal_lines import StopLine
from macromicro_sumo.truth.stations import Piece, full_stations, ramp_between, station_speeds

STOP_BAR_REACH_M = 5.0
"""A station at most this far before a stop line is its stop bar (the tool's boundary
station sits ``stations.STOP_BAR_M``, 0.5 m, before it): it sees the queue leave at green."""

CLEAR_QUANTILE = 0.5
"""Which of the intervals' bounds' lower bounds on an approach's constant is taken (0.5:
the median). The largest, over the bounds and the ends of green as before, picked the
within-interval spread's errors: on arterials with other programs and intervals than the
tuned ones' (90 s, 90 s) +2 to +11 vehicles per lane."""

AFTER_LINE_M = 50.0
"""An approach's up station at most this far past the previous stop line sees that signal's
platoons: its count is timed by that signal's program."""

WAVE_MPS = 6.8
"""How fast the start of green runs back up a standing queue (SUMO's cars: 5 m long, 2.5 m
gap, one starting about every 1.1 s)."""

QUEUED_MPS = (5.0, 10.0)
"""An up station's interval speed at or below which it stands in the queue (its passages
come when the green's wave reaches it), at or above which it flows; linear between."""

QUEUE_REACH_MPS = 7.0
"""A station on an approach (not its stop bar, nor within ``AFTER_LINE_M`` past the
previous signal, whose discharge crosses it slowly) whose interval speed is at or below
this has the queue reach back over it. At 5 m/s (the occupancy threshold) a queue that
reaches a loop only briefly was missed (arterial 602's middle approach, 6.4-8.2 m/s)."""


@dataclass(frozen=True)
class Approach:
    """The counted stretch before a stop line: its stations and the line's program."""

    up_m: float
    bar_m: float
    line: StopLine
    before: tuple[float, StopLine] | None = None  # the stop bar and line the up station follows


def approaches(
    det: pd.DataFrame, section: Section, lines: list[StopLine], side_arcs: np.ndarray
) -> list[Approach]:
    """Each stop line's approach (``Approach``) where a station counts every lane within
    ``STOP_BAR_REACH_M`` before it and another before that, past the previous junction, with
    no ramp or side street between them. (The stretch past the last signal, counted so, was
    worse than the density estimate: arterials 2, 600, 601, 603 0.5-1.2 vehicles per lane.)"""
    arcs = full_stations(det, section)

    def bar_of(line: StopLine) -> np.ndarray:
        return arcs[(arcs <= line.arc_m) & (arcs >= line.arc_m - STOP_BAR_REACH_M)]

    out: list[Approach] = []
    prev: StopLine | None = None
    for line in lines:
        ends = bar_of(line)
        ups = arcs[arcs > prev.arc_m] if prev is not None else arcs
        if len(ends) and len(ups) and ups[0] < ends[-1]:
            up, bar = float(ups[0]), float(ends[-1])
            before = None
            if prev is not None and len(bar_of(prev)) and up - prev.arc_m <= AFTER_LINE_M:
                before = (float(bar_of(prev)[-1]), prev)
            if not ramp_between(side_arcs, up, bar):
                out.append(Approach(up, bar, line, before))
        prev = line
    return out


def station_counts(det: pd.DataFrame, arc: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A station's intervals (begin, end) and its count over its lanes in each."""
    g = det[(det["arc_m"] == arc) & (det["kind"] == "e1")]
    per = g.groupby(["begin_s", "end_s"], sort=True)["n_veh"].sum()
    b = per.index.get_level_values(0).to_numpy(float)
    return b, per.index.get_level_values(1).to_numpy(float), per.to_numpy(float)


def cumulative(
    det: pd.DataFrame,
    arc: float,
    at_s: np.ndarray,
    line: StopLine | None = None,
    share: np.ndarray | None = None,
) -> np.ndarray:
    """A station's cumulative count at ``at_s``: exact at its intervals' bounds, spread
    within each over its signal's passing seconds (``line``) or evenly (None). With
    ``share`` (per interval, 0-1), that share of each interval's count passes while
    ``line`` lets pass, the rest while it stops the section's lanes (the side streets
    turning in)."""
    begin, end, n = station_counts(det, arc)
    cum = np.concatenate([[0.0], np.cumsum(n)])
    t = np.clip(np.asarray(at_s, dtype=float), begin[0], end[-1])
    j = np.clip(np.searchsorted(begin, t, side="right") - 1, 0, len(n) - 1)
    even = (t - begin[j]) / (end[j] - begin[j])
    if line is None:
        return cum[j] + even * n[j]
    g0, g1, gt = line.green_s(begin[j]), line.green_s(end[j]), line.green_s(t)
    span = g1 - g0
    frac = np.where(span > 0, (gt - g0) / np.where(span > 0, span, 1.0), even)
    if share is None:
        return cum[j] + frac * n[j]
    red = (end[j] - begin[j]) - span
    red_frac = np.where(red > 0, ((t - begin[j]) - (gt - g0)) / np.where(red > 0, red, 1.0), even)
    s = share[j]
    return cum[j] + (s * frac + (1.0 - s) * red_frac) * n[j]


def queued_share(det: pd.DataFrame, arc: float) -> np.ndarray:
    """Per interval of a station, how far it stands in a queue: its interval speed (over its
    lanes, ``stations.station_speeds``) through ``QUEUED_MPS`` (1 at or below the first)."""
    e1 = det[(det["arc_m"] == arc) & (det["kind"] == "e1")]
    speeds = [float(station_speeds(g).iloc[0]) for _, g in e1.groupby("begin_s", sort=True)]
    return occupancy_weight(np.array(speeds), *QUEUED_MPS)


def arrivals(det: pd.DataFrame, a: Approach, at_s: np.ndarray) -> np.ndarray:
    """The approach's cumulative arrivals at its up station: past a signal (``a.before``)
    the previous stop bar's count while that signal lets pass, the rest (side streets
    turning in) while it stops; else evenly spread where the up station flows, and while
    its own line lets pass, ``WAVE_MPS`` later, where the queue reaches back over it."""
    if a.before is not None:
        bar, line = a.before
        n_up, n_bar = station_counts(det, a.up_m)[2], station_counts(det, bar)[2]
        share = np.where(n_up > 0, np.minimum(n_bar, n_up) / np.where(n_up > 0, n_up, 1.0), 1.0)
        return cumulative(det, a.up_m, at_s, line, share)
    even = cumulative(det, a.up_m, at_s)
    late = replace(a.line, offset_s=a.line.offset_s + (a.line.arc_m - a.up_m) / WAVE_MPS)
    begin = station_counts(det, a.up_m)[0]
    j = np.clip(np.searchsorted(begin, np.asarray(at_s, dtype=float), side="right") - 1, 0, None)
    w = queued_share(det, a.up_m)[j]
    return even + w * (cumulative(det, a.up_m, at_s, late) - even)


def queue_floor(
    det: pd.DataFrame, e1: pd.DataFrame, section: Section, a: Approach, spacing_m: float
) -> list[tuple[float, float]]:
    """``(t, vehicles)``: the fewest vehicles on the approach at each start of green ``t``
    in the interval of ``e1`` (one interval's rows) where a queue stands on it; [] where
    none does. A station (not the stop bar) whose interval speed is at or below
    ``QUEUE_REACH_MPS`` has the queue's farthest reach at or past it (the approach's whole
    length where that is its up station). That reach comes after the start of green
    (Lighthill-Whitham: the queue's back runs up at ``w``, the arrival flow over the jam
    density less the arrivals', until the start of green, running back at ``WAVE_MPS``,
    meets it), so at the start of green the queue stands at least that reach times
    ``1 - w / WAVE_MPS``; the arrival flow: the vehicles that crossed the up station during
    the red (``arrivals``). Count: that station's lanes whose loop reads the queue (a lane
    may turn off freely) x that length / ``spacing_m``, and the rest of
    the approach: at an entry (steady arrivals) its stations' interval density outside the
    queue; past a signal (platoons: the interval density over-counts the start of green)
    the vehicles that crossed the up station within the free travel to the queue's back."""
    arcs = full_stations(e1, section)
    arcs = arcs[(arcs >= a.up_m) & (arcs < a.line.arc_m - STOP_BAR_REACH_M)]
    if a.before is not None:  # past a signal: its discharge crosses slowly
        arcs = arcs[arcs > a.before[1].arc_m + AFTER_LINE_M]
    speeds = station_speeds(e1[e1["arc_m"].isin(arcs)]).reindex(arcs).to_numpy(dtype=float)
    queued = np.flatnonzero(speeds <= QUEUE_REACH_MPS)
    if not len(queued):
        return []
    far = float(arcs[int(queued[0])])  # arcs ascend
    reach = a.line.arc_m - max(far, a.up_m)
    loops = e1[(e1["arc_m"] == far) & (e1["kind"] == "e1")]
    stand = int(((loops["n_veh"] == 0) | (loops["speed_mps"] <= QUEUE_REACH_MPS)).sum())
    e = section.edge_index(np.array([a.bar_m]))[0]
    lanes, v_free = int(section.n_lanes[e]), float(np.nanmax(section.limits_mps[e]))
    per_station = station_density(e1, section)
    b, end = float(e1["begin_s"].iloc[0]), float(e1["end_s"].iloc[0])
    out = []
    for t, red in a.line.green_starts(b, end):
        flow = max(float(np.diff(arrivals(det, a, np.array([t - red, t])))[0]), 0.0) / lanes / red
        w = flow / max(1.0 / spacing_m - flow / v_free, 1e-6)
        length = reach * float(np.clip(1.0 - w / WAVE_MPS, 0.0, 1.0))
        back = a.line.arc_m - length
        if a.before is None:  # steady arrivals: the stations' interval density outside
            outside = per_station[per_station.index.to_numpy(dtype=float) < back]
            rest = integrate_stations(outside, section, a.up_m, back) if len(outside) else 0.0
        else:  # platoons: those that crossed the up station within the travel to the back
            travel = (back - a.up_m) / v_free
            rest = float(np.diff(arrivals(det, a, np.array([t - travel, t])))[0])
        out.append((t, min(stand, lanes) * length / spacing_m + max(rest, 0.0)))
    return out


def queue_constant(det: pd.DataFrame, section: Section, a: Approach, io, spacing_m: float) -> float:
    """The ``CLEAR_QUANTILE`` over the starts of green where a queue stands of the fewest
    vehicles there (``queue_floor``, at jam spacing ``spacing_m``) less ``io``: a lower
    bound on the approach's constant; -inf where no queue stands."""
    floors = [
        floor
        for _, e1 in det[det["kind"] == "e1"].groupby(["begin_s", "end_s"], sort=True)
        for floor in queue_floor(det, e1, section, a, spacing_m)
    ]
    if not floors:
        return -np.inf
    t, n = np.array(floors).T
    return float(np.quantile(n - io(t), CLEAR_QUANTILE))


def density_constant(
    det: pd.DataFrame,
    section: Section,
    a: Approach,
    io,
    spacing_m: float | None = None,
    share: float = 1.0,
    by_station: bool = False,
) -> float:
    """The constant that puts the counted approach ``a`` (``io(t)`` plus it) on its density
    estimate on average over the record: the mean over the intervals of the stations'
    density integrated over the approach less ``io``'s mean over the interval. Dual loops:
    their occupancy's density (``section_macro.edie_densities``), rising toward the line as
    ``density.rising_integral`` (docs/sections-log.md, "Dual loops on signal approaches").
    Point loops with ``spacing_m``: the stations near the line with the red's standing queue
    added (``standing.standing_density``, times ``share``, ``by_station`` by ``seen_share``;
    the vehicles arriving at the line in the red: ``arrivals`` a free travel earlier)."""
    e1s, rows = det[det["kind"] == "e1"], []
    dual = bool((loop_lengths_m(e1s) > 0).any())
    e = section.edge_index(np.array([a.bar_m]))[0]
    lanes, v_free = int(section.n_lanes[e]), float(np.nanmax(section.limits_mps[e]))
    travel = (a.line.arc_m - a.up_m) / v_free
    for (b, e), e1 in (edie_densities(e1s) if dual else e1s).groupby(["begin_s", "end_s"]):
        k = station_density(e1, section)
        if spacing_m is not None and not dual:
            reds = [
                (float(np.diff(arrivals(det, a, np.array([t - r, t]) - travel))[0]), r)
                for t, r in a.line.green_starts(b, e)
            ]
            q = (reds, e - b, lanes, spacing_m, v_free, WAVE_MPS)
            k = standing.near_line_profile(k, e1, a.line.arc_m, a.up_m, q, share, by_station)
        if dual:
            k = rising_integral(k.index.to_numpy(dtype=float), k.to_numpy(), a.up_m, a.bar_m)
        else:
            k = integrate_stations(k, section, a.up_m, a.bar_m)
        rows.append(k - float(np.mean(io(np.linspace(b, e, 7)))))
    return float(np.mean(rows))


def approach_count(
    det: pd.DataFrame,
    section: Section,
    a: Approach,
    at_s: np.ndarray,
    spacing_m: float,
    near_line: bool | str = False,
) -> np.ndarray | None:
    """Vehicles on the approach ``a`` at ``at_s`` by conservation, anchored on the density
    estimate and the lower bounds at the intervals' bounds (module doc; a standing queue's
    at jam spacing ``spacing_m``, ``jam_spacing_m``); None where the counts drift past what
    it can hold. ``near_line``: where the free-travel bound is the largest (no station reads
    a queue), the density estimate with the near-line loops' standing queue added; "all" or
    "station": every approach's, with ``standing.near_line_share`` of it added."""
    begin, end, _ = station_counts(det, a.bar_m)
    length = a.bar_m - a.up_m
    e = section.edge_index(np.array([a.bar_m]))[0]
    travel_s = length / float(np.nanmax(section.limits_mps[e]))
    lanes = int(section.n_lanes[e])
    bounds = np.concatenate([begin, end[-1:]])
    t = bounds[bounds >= begin[0] + travel_s]

    def io(x: np.ndarray) -> np.ndarray:
        return arrivals(det, a, x) - cumulative(det, a.bar_m, x, a.line)

    if len(t) == 0:
        return None
    moving = arrivals(det, a, t) - arrivals(det, a, t - travel_s)
    mov = float(np.quantile(moving - io(t), CLEAR_QUANTILE))
    share = standing.near_line_share(near_line)  # a share on every approach
    every, near = share is not None, (spacing_m, *share) if share is not None else ()
    dens = density_constant(det, section, a, io, *near)
    others = (dens, queue_constant(det, section, a, io, spacing_m))
    low = max(mov, *others, -float(io(bounds).min()))
    if near_line and not every and low == mov and mov > max(others):
        low = max(low, density_constant(det, section, a, io, spacing_m))
    room = lanes * length / JAM_SPACING_M
    high = room - float(io(bounds).max())
    if low > high:
        return None
    return np.maximum(low + io(np.asarray(at_s, dtype=float)), 0.0)


def exit_stretch(
    det: pd.DataFrame, section: Section, lines: list[StopLine], side_arcs: np.ndarray
) -> Approach | None:
    """The stretch from the first station past the last stop line to the last station
    (its ``line`` the last signal's, its ``before`` that signal's stop bar), or None where
    there is none or a ramp lies between them."""
    arcs = full_stations(det, section)
    last = lines[-1]
    ups, bars = (
        arcs[arcs > last.arc_m],
        arcs[(arcs <= last.arc_m) & (arcs >= last.arc_m - STOP_BAR_REACH_M)],
    )
    if len(ups) < 2 or ramp_between(side_arcs, float(ups[0]), float(ups[-1])):
        return None
    before = (float(bars[-1]), last) if len(bars) and ups[0] - last.arc_m <= AFTER_LINE_M else None
    return Approach(float(ups[0]), float(ups[-1]), last, before)


def free_count(det: pd.DataFrame, a: Approach, at_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vehicles on the stretch ``a`` at ``at_s`` while it flows: those that crossed its up
    station within the travel time at its two stations' interval speed (harmonic), and per
    time the weight of its density estimate instead: the more queued station's
    ``queued_share``)."""
    speeds = []
    for arc in (a.up_m, a.bar_m):
        e1 = det[(det["arc_m"] == arc) & (det["kind"] == "e1")]
        speeds.append(
            [float(station_speeds(g).iloc[0]) for _, g in e1.groupby("begin_s", sort=True)]
        )
    v = np.array(speeds)
    ok = (v > 0).all(axis=0)
    harmonic = np.where(
        ok, 2.0 / np.where(ok, 1.0 / np.where(v > 0, v, 1.0), 1.0).sum(axis=0), np.nan
    )
    begin = station_counts(det, a.up_m)[0]
    at = np.asarray(at_s, dtype=float)
    j = np.clip(np.searchsorted(begin, at, side="right") - 1, 0, len(begin) - 1)
    w = np.maximum(queued_share(det, a.up_m), queued_share(det, a.bar_m))[j]
    w = np.where(np.isfinite(harmonic[j]), w, 1.0)
    travel = (a.bar_m - a.up_m) / np.where(np.isfinite(harmonic[j]), harmonic[j], 1.0)
    return arrivals(det, a, at) - arrivals(det, a, at - travel), w


def approach_pieces(
    det: pd.DataFrame,
    section: Section,
    lines: list[StopLine],
    side_arcs: np.ndarray,
    run: int,
    at_s: np.ndarray,
    near_line: bool | str = False,
) -> tuple[dict[str, Piece], pd.DataFrame]:
    """The approaches counted at ``at_s`` (``approach_count``) and the stretch past the last
    signal (``exit_stretch``, ``free_count``) as pieces, and per interval the density
    estimate of the rest of the section (``begin_s, end_s, vehicles``), as
    ``hidden_count.io_pieces`` gives them (``near_line``: ``approach_count``'s)."""
    d = det[det["run"] == run]
    at = np.asarray(at_s, dtype=float)
    counted, spans = np.zeros(len(at)), []
    spacing = standing.jam_spacing_m(d)  # the run's loops, once for its approaches
    for a in approaches(d, section, lines, side_arcs):
        n = approach_count(d, section, a, at, spacing, near_line)
        if n is not None:
            counted += n
            spans.append((a.up_m, a.bar_m))
    tail = exit_stretch(d, section, lines, side_arcs)
    rest, tail_dens = [], []
    # Dual loops' stop bars read the queue: the rest's density steps at each stop line.
    cut = [line.arc_m for line in lines] if (loop_lengths_m(d) > 0).any() else []
    for (begin, end), e1 in d[d["kind"] == "e1"].groupby(["begin_s", "end_s"], sort=True):
        per_station = cut_at_lines(station_density(e1, section), cut)
        inside = sum(integrate_stations(per_station, section, lo, hi) for lo, hi in spans)
        if tail is not None:
            tail_dens.append(integrate_stations(per_station, section, tail.up_m, tail.bar_m))
            inside += tail_dens[-1]
        total = integrate_stations(per_station, section)
        rest.append({"begin_s": begin, "end_s": end, "vehicles": total - inside})
    pieces = {"approaches": Piece(tuple(spans), counted)} if spans else {}
    if tail is not None:
        free, w = free_count(d, tail, at)
        begin = station_counts(d, tail.up_m)[0]
        j = np.clip(np.searchsorted(begin, at, side="right") - 1, 0, len(begin) - 1)
        dens = np.array(tail_dens)[j]
        pieces["exit"] = Piece(((tail.up_m, tail.bar_m),), (1.0 - w) * free + w * dens)
    return pieces, pd.DataFrame(rest, columns=["begin_s", "end_s", "vehicles"])

"""Traffic density from loop detectors and the vehicle count of a road section from it:
pure functions, no SUMO, no pandas.

Point density of one loop in one interval (veh/km per lane), by speed regime:
- **free flow**: flow / harmonic-mean speed (k = q / v_s, the fundamental relation with the
  space-mean speed, which is the harmonic mean of the spot speeds);
- **collapsed speeds** (queues): occupancy / effective vehicle length (k = o / (L + l_loop),
  the single-loop method). Where vehicles crawl or stand over a loop, the few passages give
  a poor space-mean speed and a standing vehicle gives no passage at all, but the loop is
  occupied the whole time it stands there;
- between the two thresholds the two are blended linearly, so that the estimate does not
  jump when the interval's speed crosses one.

Along the section: each station (the loops at one arc) gives a density over all its lanes
(the mean of its reporting lanes times its lane count: a missing lane is imputed from its
neighbours at the station, as a lane-ratio fill does); that density is linear in arc
between stations, constant beyond the outermost stations of an open section and periodic
on a closed one, and is integrated along the arc. The density over all lanes, not per
lane, is what carries across a lane drop or gain: the same flow at the same speed has the
same density whether it uses one lane or three.

Within an interval the count moves faster than any 30-60 s aggregate follows (platoons,
signal cycles, a queue growing): the per-vehicle passages of stations that cover every lane
give the count between two stations exactly up to a constant (vehicles in = passages at the
upstream station, out = at the downstream one: the input-output method), and the constant
is taken from the density estimate, weighted to its free-flowing intervals (where flow /
speed is right; a loop in a queue does not stand for its cell): one constant for the whole
record where no ramp lies between the stations, a line over a window where one may (drift
correction); a simulation's loops count from its empty start, where the count needs no
constant at all (``hidden_count.io_pieces``). An open section's end pieces, beyond its
outermost stations, are counted from the passages there, each vehicle projected at the
speed it passed with.
"""

from __future__ import annotations

import numpy as np

SPEED_OCCUPANCY_BELOW_MPS = 5.0
"""At or below this interval speed (m/s), or where no vehicle passed, the density is the
occupancy's: queues and stop-and-go."""
SPEED_FLOW_ABOVE_MPS = 10.0
"""At or above this interval speed (m/s) the density is flow / harmonic-mean speed; in
between, a linear blend. Both thresholds sit far below a motorway's or an arterial's free
speed and above a queue's crawl; on SUMO's loops both estimates agree within ~1% in free
flow, so the blend only matters where speeds collapse."""
DEFAULT_VEHICLE_LENGTH_M = 5.0
"""Vehicle length where a loop saw no vehicle to measure one on (SUMO's passenger car)."""


def flow_speed_density(flow_vph: np.ndarray, speed_mps: np.ndarray) -> np.ndarray:
    """k = q / v_s in veh/km; NaN where no speed was measured (no vehicle passed)."""
    q = np.asarray(flow_vph, dtype=float)
    v = np.asarray(speed_mps, dtype=float)
    ok = np.isfinite(v) & (v > 0)
    out = np.full(np.broadcast(q, v).shape, np.nan)
    np.divide(q / 3.6, v, out=out, where=ok)
    return out


def occupancy_density(
    occupancy_pct: np.ndarray, vehicle_length_m: np.ndarray, loop_length_m: float = 0.0
) -> np.ndarray:
    """k = occupancy / (vehicle length + loop length) in veh/km (a vehicle occupies a loop
    while any part of it is over it, hence the loop's own length; SUMO's E1 loop is a
    point, length 0)."""
    occ = np.asarray(occupancy_pct, dtype=float) / 100.0
    return occ / (np.asarray(vehicle_length_m, dtype=float) + loop_length_m) * 1000.0


def occupancy_weight(
    speed_mps: np.ndarray,
    below_mps: float = SPEED_OCCUPANCY_BELOW_MPS,
    above_mps: float = SPEED_FLOW_ABOVE_MPS,
) -> np.ndarray:
    """Weight of the occupancy estimate: 1 at or below ``below_mps`` or without a speed,
    0 at or above ``above_mps``, linear in between."""
    v = np.asarray(speed_mps, dtype=float)
    w = np.clip((above_mps - v) / (above_mps - below_mps), 0.0, 1.0)
    return np.where(np.isfinite(v), w, 1.0)


def point_density(
    flow_vph: np.ndarray,
    speed_mps: np.ndarray,
    occupancy_pct: np.ndarray,
    vehicle_length_m: np.ndarray,
    loop_length_m: float = 0.0,
) -> np.ndarray:
    """One loop's density per interval (veh/km): the speed-regime blend of flow / speed and
    occupancy / effective length (see the module's docstring)."""
    w = occupancy_weight(speed_mps)
    k_occ = occupancy_density(occupancy_pct, vehicle_length_m, loop_length_m)
    k_fs = flow_speed_density(flow_vph, speed_mps)
    return np.where(w >= 1.0, k_occ, w * k_occ + (1.0 - w) * np.nan_to_num(k_fs))


def effective_length_m(
    flow_vph: np.ndarray,
    speed_mps: np.ndarray,
    occupancy_pct: np.ndarray,
    default_m: float = DEFAULT_VEHICLE_LENGTH_M,
    above_mps: float = SPEED_FLOW_ABOVE_MPS,
) -> float:
    """A loop's effective vehicle length (m: the vehicles' mean length plus the loop's own)
    from its free-flowing intervals (speed at or above ``SPEED_FLOW_ABOVE_MPS``), where flow
    / speed is the density: occupancy / that density, summed over them (each vehicle is
    over the loop for (length + loop length) / speed). ``default_m`` where none flowed
    freely. What the occupancy estimate divides by where no passage tells the lengths: a
    loop's traffic with 10 % trucks is ~12 % longer than a car."""
    q = np.asarray(flow_vph, dtype=float)
    v = np.asarray(speed_mps, dtype=float)
    occ = np.asarray(occupancy_pct, dtype=float)
    k = flow_speed_density(q, v)
    ok = np.isfinite(k) & np.isfinite(occ) & (v >= above_mps) & (k > 0)
    if not ok.any():
        return float(default_m)
    return float(occ[ok].sum() / 100.0 / (k[ok].sum() / 1000.0))


def _stations_by_arc(
    station_arcs_m: np.ndarray, k_vpkm: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The stations with a finite density, in arc order: arcs [m] and densities [veh/m]."""
    a = np.asarray(station_arcs_m, dtype=float)
    k = np.asarray(k_vpkm, dtype=float) / 1000.0
    ok = np.isfinite(k)
    order = np.argsort(a[ok])
    return a[ok][order], k[ok][order]


def profile_integral(
    station_arcs_m: np.ndarray,
    k_vpkm: np.ndarray,
    length_m: float,
    closed: bool,
    lo_m: float = 0.0,
    hi_m: float | None = None,
) -> float:
    """Vehicles on [lo_m, hi_m] (default: the whole section) when the density (veh/km over
    all lanes) is linear in arc between stations, constant beyond the outermost ones of an
    open section and periodic on a closed one: the trapezoid rule, exact for it."""
    a, k = _stations_by_arc(station_arcs_m, k_vpkm)
    if a.size == 0:
        return float("nan")
    hi = float(length_m) if hi_m is None else float(hi_m)
    if closed:
        # One station before the first and one after the last, a lap away: periodic.
        a = np.concatenate([a[-1:] - length_m, a, a[:1] + length_m])
        k = np.concatenate([k[-1:], k, k[:1]])
    grid = np.unique(np.concatenate([a, [lo_m, hi]]))
    grid = grid[(grid >= lo_m) & (grid <= hi)]
    dens = np.interp(grid, a, k)  # constant beyond the ends of an open section
    return float((0.5 * (dens[1:] + dens[:-1]) * np.diff(grid)).sum())


RISE_POWER = 2.0
"""How a signal approach's time-mean density rises between two stations toward the stop line
(``rising_integral``): as the power 2 of the way from the lower station to the higher, not
linearly. A queue's back, where the density steps up, swings over a few tens of metres about
where the queue holds in the cycle, nearer the station that reads the queue than the chord
puts it (fresh arterial 769 from 240 s, the approach 590-844 m: the true density steps up
at 720-740 m between stations at 650 and 750 m; the approach's constant on the chord 4.3 and
4.7 vehicles high in its two runs, with the power 2 1.8 and 2.1; picked on 769 and 770, then
measured on 741-760, 761-780, 801-820 and the tuned set: docs/sections-log.md, "Dual loops on signal approaches")."""


def rising_integral(
    station_arcs_m: np.ndarray, k_vpkm: np.ndarray, lo_m: float, hi_m: float
) -> float:
    """Vehicles on [lo_m, hi_m] from the stations' densities (veh/km over all lanes; the
    profile between them as ``profile_integral``'s) where the density rises from one station
    to the next as ``RISE_POWER`` of the way (a stretch's mean: the lower density plus the
    rise over ``RISE_POWER + 1``) and falls linearly."""
    a, k = _stations_by_arc(station_arcs_m, k_vpkm)
    if a.size == 0:
        return float("nan")
    grid = np.unique(np.concatenate([a, [lo_m, hi_m]]))
    grid = grid[(grid >= lo_m) & (grid <= hi_m)]
    dens = np.interp(grid, a, k)
    lower, upper = dens[:-1], dens[1:]
    rise = np.where(
        upper > lower, lower + (upper - lower) / (RISE_POWER + 1.0), 0.5 * (lower + upper)
    )
    return float((rise * np.diff(grid)).sum())


def cumulative_count(passage_times_s: np.ndarray, at_s: np.ndarray) -> np.ndarray:
    """Passages strictly before each time of ``at_s`` (a loop's cumulative count)."""
    t = np.sort(np.asarray(passage_times_s, dtype=float))
    return np.searchsorted(t, np.asarray(at_s, dtype=float), side="left").astype(float)


def cumulative_mean(passage_times_s: np.ndarray, begin_s: float, end_s: float) -> float:
    """Time mean over [begin_s, end_s) of a loop's cumulative count (``cumulative_count``),
    exactly: the count at ``begin_s`` plus each passage inside for the rest of the span."""
    t = np.asarray(passage_times_s, dtype=float)
    inside = t[(t >= begin_s) & (t < end_s)]
    base = float((t < begin_s).sum())
    return base + float((end_s - inside).sum()) / (end_s - begin_s)


def anchored_counts(
    io_counts: np.ndarray,
    io_means: np.ndarray,
    density_counts: np.ndarray,
    interval_centres_s: np.ndarray,
    at_s: np.ndarray,
    window_s: float,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Input-output counts made absolute: ``io_counts`` (at ``at_s``, known up to a constant)
    plus (density estimate - input-output mean) over the intervals whose centres lie within
    ``window_s`` / 2 of each time (the nearest interval where none does), fitted by a line
    in time (``local_line``, weighted by ``weights``) and taken at that time. An infinite
    ``window_s`` fits one weighted mean over every interval: a stretch nothing enters or
    leaves between its stations has one constant for the whole record.

    The density estimate is right on average but follows neither platoons nor signal cycles
    within an interval; the input-output count follows them exactly but drifts where
    vehicles enter or leave between stations or a count is missed. The window's offset
    keeps the second's timing and the first's level.
    """
    c = np.asarray(interval_centres_s, dtype=float)
    off = np.asarray(density_counts, dtype=float) - np.asarray(io_means, dtype=float)
    w = np.ones_like(c) if weights is None else np.asarray(weights, dtype=float)
    ok = np.isfinite(off) & np.isfinite(w) & (w > 0)
    c, off, w = c[ok], off[ok], w[ok]
    out = np.full(len(np.atleast_1d(at_s)), np.nan)
    if c.size == 0:
        return out
    if not np.isfinite(window_s):
        return io_counts + float(np.average(off, weights=w))
    for i, t in enumerate(np.atleast_1d(np.asarray(at_s, dtype=float))):
        near = np.abs(c - t) <= window_s / 2
        if not near.any():
            near = np.abs(c - t) == np.abs(c - t).min()
        out[i] = io_counts[i] + local_line(c[near], off[near], t, w[near])
    return out


def local_line(x: np.ndarray, y: np.ndarray, at: float, weights: np.ndarray | None = None) -> float:
    """The (weighted) least-squares line through (x, y) evaluated at ``at``; the mean where
    fewer than three points or no spread in x. An unmeasured ramp between two stations
    makes their input-output count drift at its flow: a line follows that drift to a
    window's end, where a mean would lag by half the window's drift."""
    w = np.ones(len(x)) if weights is None else np.asarray(weights, dtype=float)
    if len(x) < 3 or np.ptp(x) == 0:
        return float(np.average(y, weights=w))
    slope, intercept = np.polyfit(x, y, 1, w=np.sqrt(w))
    return float(intercept + slope * at)


FREE_WEIGHT_FLOOR = 0.02
"""A queued interval's weight as an anchor (``free_flow_weight``)."""


def free_flow_weight(speed_mps: np.ndarray, floor: float = FREE_WEIGHT_FLOOR) -> np.ndarray:
    """Weight of an interval's density estimate as an anchor for input-output counts: 1 in
    free flow (speed at or above ``SPEED_FLOW_ABOVE_MPS``, where flow / speed is within
    ~1%), ``floor`` in queues (the loop's density stands for its whole cell there, which a
    queue ending between stations is not), linear in between. The floor keeps a record
    that is congested throughout anchored."""
    return np.maximum(1.0 - occupancy_weight(speed_mps), floor)


def projected_passages(
    passage_s: np.ndarray,
    speed_mps: np.ndarray,
    at_s: np.ndarray,
    distance_m: float,
    upstream: bool,
    min_speed_mps: float = 0.5,
) -> np.ndarray:
    """Vehicles within ``distance_m`` of a station at each time of ``at_s``, from its
    per-vehicle passages, each vehicle at the speed it passed with: upstream, those that
    pass it within distance / speed after; downstream, those that passed it within
    distance / speed before. This counts an open section's end pieces (beyond its outermost
    stations) at the snapshot's time, where an interval's density averages over a minute.
    Speeds below ``min_speed_mps`` count as it (a crawl over the loop)."""
    p = np.asarray(passage_s, dtype=float)
    reach = distance_m / np.maximum(np.asarray(speed_mps, dtype=float), min_speed_mps)
    t = np.atleast_1d(np.asarray(at_s, dtype=float))
    order = np.argsort(t)
    ts = t[order]
    # Each passage counts at the times of one span: upstream [p - reach, p) (it passes
    # after t, within reach), downstream [p, p + reach); summed by a difference array.
    lo, hi = (p - reach, p) if upstream else (p, p + reach)
    steps = np.zeros(len(ts) + 1)
    np.add.at(steps, np.searchsorted(ts, lo, "left"), 1.0)
    np.add.at(steps, np.searchsorted(ts, hi, "left"), -1.0)
    out = np.empty(len(ts))
    out[order] = np.cumsum(steps)[:-1]
    return out


def node_projection(
    into_s: np.ndarray,
    into_mps: np.ndarray,
    out_s: np.ndarray,
    out_mps: np.ndarray,
    at_s: np.ndarray,
    metres: tuple[float, float, float],
) -> np.ndarray:
    """Vehicles at the times ``at_s`` on a short stretch over a node where vehicles turn
    off and on (a signal's junction, a ramp's), from its stations' passages (times and
    speeds: ``into`` upstream, ``out`` downstream), each vehicle at the speed it passed
    with (``projected_passages``). ``metres``: from the upstream station to the node's
    line, over the junction, from its end to the downstream station. Up to the line, those
    that passed ``into`` within that distance / speed before (one turning off is on the
    section there); past the junction, those that pass ``out`` within it after (one that
    turned on is there); over the junction the fewer of the two stations' projections,
    since ``into``'s hold those turning off too and ``out``'s those turning on, which flow
    at other times (at red the stop bar sees no one while the side street turns on).
    Neither station's count is needed, so the turning flows need not be known."""
    before, over, after = metres

    def into(m: float) -> np.ndarray:
        return projected_passages(into_s, into_mps, at_s, m, upstream=False)

    def out(m: float) -> np.ndarray:
        return projected_passages(out_s, out_mps, at_s, m, upstream=True)

    return (
        into(before)
        + np.minimum(into(before + over) - into(before), out(over + after) - out(after))
        + out(after)
    )


JAM_SPACING_M = 5.0
"""The shortest room a vehicle takes in a standing queue (a 5 m car, no gap): a stretch
holds at most ``stretch_room`` vehicles (``sealed_count``)."""


def stretch_room(length_m: float, lanes: int) -> int:
    """The most vehicles whose fronts lie between two stations ``length_m`` apart on
    ``lanes`` lanes: per lane one every ``JAM_SPACING_M`` and one more, since a front
    already counted in can stand before the downstream loop however short the stretch
    (two stations 2-4 m apart on a 2-lane arterial hold 2 vehicles, and their lane-metres
    / 5 m, 0.7-1.7, rejected an exact count: drawn arterials 1161 and 1407, stop 47)."""
    return int(lanes) * (int(np.floor(length_m / JAM_SPACING_M)) + 1)


def sealed_count(into_s: np.ndarray, out_s: np.ndarray, length_m: float, lanes: int) -> bool:
    """Whether a stretch's count since the empty start, the passages ``into_s`` at its
    upstream station less ``out_s`` at its downstream one, stays a possible count after
    every passage: never below 0 (a vehicle came in from a side road) and never above
    ``stretch_room`` (vehicles that entered left by one)."""
    t = np.concatenate([np.asarray(into_s, dtype=float), np.asarray(out_s, dtype=float)])
    step = np.concatenate([np.ones(len(into_s)), -np.ones(len(out_s))])
    n = np.cumsum(step[np.lexsort((-step, t))])  # at one time, the entry first
    return bool(n.size == 0 or (n.min() >= 0 and n.max() <= stretch_room(length_m, lanes)))

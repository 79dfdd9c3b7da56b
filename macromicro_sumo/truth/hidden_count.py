"""The hidden count K of a section per snapshot from its detectors: the stretches between
stations that count every vehicle (input-output counts from the per-vehicle passages),
the end pieces of an open section (passages projected at their speeds) and the density
estimate of the rest (``section_macro``), beside the truth the simulation knows
(docs/sections.md, "Hidden count").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import at_snapshot_times
from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.density import (
    JAM_SPACING_M,
    anchored_counts,
    cumulative_count,
    cumulative_mean,
    free_flow_weight,
    node_projection,
    occupancy_weight,
    projected_passages,
    sealed_count,
)
from macromicro_sumo.truth.section_macro import (
    K_ESTIMATE_COLUMNS,
    integrate_stations,
    loop_densities,
    station_density,
)
from macromicro_sumo.truth.signal_counts import approach_pieces
from macromicro_sumo.truth.stations import (
    Piece,
    StationRecord,
    full_stations,
    ramp_between,
    station_passages,
    station_speeds,
    stretch_m,
)

IO_ANCHOR_WINDOW_S = 180.0
"""Window of the line by which the stretches' summed input-output count takes its level
from the density estimate (``density.anchored_counts``) where a ramp lies between two
stations: the count drifts at the ramps' net flow, which changes with the demand and the
queues. On the bench 180 s against 60, 120, 300, 450 and 600 s (docs/sections.md,
"Hidden count")."""


EMPTY_START_TOLERANCE_VEH = 3.0
EMPTY_START_TOLERANCE = 0.05
"""A simulation starts with an empty network and its loops count from its first step: the
input-output count between full stations is then the count, exactly, unless vehicles
depart or arrive between them. The density estimate's offset to it (free-flow weighted,
``density.anchored_counts``) is its check: within 3 vehicles or 5% of the stretches' count
it is the density estimate's own error (on the bench -1.6 to +5.8 vehicles, 1-5%), beyond
it the count drifts and the offset is taken instead."""


SHORT_STRETCH_M = 100.0
"""A stretch with a ramp at most this long between its stations (the boundary stations
either side of a ramp's node: 30 m plus the junction) is estimated from its stations'
passages each side of the node (``density.node_projection``); a longer one from its
input-output count, anchored by a line (``io_pieces``)."""


def io_pieces(
    record: StationRecord, section: Section, run: int, at_s: np.ndarray
) -> tuple[dict[str, Piece], pd.DataFrame]:
    """The parts of the section counted from the passages at the times ``at_s``, by name,
    and per interval the density estimate of the rest of the section (``begin_s, end_s,
    vehicles``; all of it where no station counts every vehicle).

    Stretches between consecutive full stations: ``stretches``, their summed input-output
    count anchored to their density estimate, each stretch's offset weighted to the
    intervals in which it flows freely: by one constant for the whole record where no ramp
    lies between two stations (``side_arcs``, arcs of the nodes with ramps; None: unknown,
    every stretch may hold one), else by a line over ``IO_ANCHOR_WINDOW_S`` (the count
    drifts at the ramps' net flow). With ``from_empty`` (the passages start with an empty
    section: a simulation from its first step) on an open section, ``between``, the
    stretches with no ramp, are their input-output count itself (nothing enters or leaves
    them but through their stations), where the density estimate's offset to it agrees
    within ``EMPTY_START_TOLERANCE_VEH`` or ``EMPTY_START_TOLERANCE`` of their count;
    ``ramps``, the others, are anchored as ``stretches`` are, but for the short stretches
    around a ramp's node: ``node_counts``, their count where nobody turned there
    (``sealed_count``), else ``ramp_nodes``, their stations' passages projected each
    side of the node (``density.node_projection``). On an open section ``upstream`` and
    ``downstream``, the end pieces beyond the outermost full stations
    (``density.projected_passages``; upstream blended with the density estimate by the
    station's speed, since a vehicle queued there passes slower than it drove).
    ``passage_lag_s``: how far the passages' clock runs behind the times ``at_s``
    (``PASSAGE_LAG_STEPS``).
    """
    det, passages, side_arcs = record.det, record.passages, record.side_arcs
    d = det[det["run"] == run]
    at_p = np.asarray(at_s, dtype=float) - record.passage_lag_s  # the same moments, passages' clock
    p = passages[passages["run"] == run]
    arcs = full_stations(d, section)
    pairs = list(zip(arcs[:-1], arcs[1:], strict=True))
    if section.closed and len(arcs) > 1:
        pairs.append((arcs[-1], arcs[0]))
    if record.interval_counts and side_arcs is not None:  # a short one with a ramp: its
        # count drifts at the ramp's flow within each interval; left to the density estimate
        pairs = [
            q
            for q in pairs
            if stretch_m(q, section) > SHORT_STRETCH_M or not ramp_between(side_arcs, *q)
        ]
    # The fastest lap, with a margin for drivers above the limit (SUMO's speedFactor).
    lap_s = section.length_m / (1.5 * float(np.nanmax(section.limits_mps)))
    own = {a: station_passages(d, p, a, lap_s) for a in arcs}
    times = {a: q["time_s"].to_numpy() for a, q in own.items()}
    intervals = d[["begin_s", "end_s"]].drop_duplicates().sort_values("begin_s")
    centres = 0.5 * (intervals["begin_s"] + intervals["end_s"]).to_numpy()
    dens = {pair: [] for pair in pairs}
    io_mean = {pair: [] for pair in pairs}
    speed = {pair: [] for pair in pairs}  # the slower station's, per interval
    ends = not section.closed and len(arcs) > 0 and not record.interval_counts
    up_dens, up_w, rest = [], [], []
    for begin, end in intervals.itertuples(index=False):
        e1 = d[(d["begin_s"] == begin) & (d["kind"] == "e1")]
        per_station = station_density(e1, section)
        speeds = station_speeds(e1)
        total = integrate_stations(per_station, section)
        inside = 0.0
        for lo, hi in pairs:
            if hi > lo:
                n = integrate_stations(per_station, section, lo, hi)
            else:  # the pair that closes the loop
                n = integrate_stations(per_station, section, lo) + integrate_stations(
                    per_station, section, 0.0, hi
                )
            dens[(lo, hi)].append(n)
            io_mean[(lo, hi)].append(
                cumulative_mean(times[lo], begin, end) - cumulative_mean(times[hi], begin, end)
            )
            speed[(lo, hi)].append(min(speeds.get(lo, 0.0), speeds.get(hi, 0.0)))
            inside += n
        if ends:
            up_dens.append(integrate_stations(per_station, section, 0.0, arcs[0]))
            up_w.append(float(occupancy_weight(np.array([speeds.get(arcs[0], 0.0)]))[0]))
            inside += up_dens[-1] + integrate_stations(per_station, section, arcs[-1])
        rest.append({"begin_s": begin, "end_s": end, "vehicles": total - inside})
    pieces: dict[str, Piece] = {}

    def anchored(
        group: list[tuple[float, float]], window_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(the group's input-output count, the same anchored to its density estimate).
        One constant for the record (``window_s`` infinite): each stretch's offset weighted
        to the intervals its own stations flow freely in, summed (the group's mean weight
        kept a queued stretch's intervals near full: drawn net 501's lane drops failed the
        empty start's check, K 1.6-1.9 per lane low; per stretch 0.01). A line over a
        window: the summed offset by the mean weight (lines per stretch were noisier: seeds
        300-307, ramps unknown, congested, 1.20 per lane against 0.97)."""
        io = [
            cumulative_count(times[lo], at_p) - cumulative_count(times[hi], at_p)
            for lo, hi in group
        ]
        total = sum(io)
        if np.isfinite(window_s):  # one line for the group: its summed count and estimate
            pieces = [
                (
                    total,
                    np.sum([io_mean[pair] for pair in group], axis=0),
                    np.sum([dens[pair] for pair in group], axis=0),
                    np.mean([free_flow_weight(np.array(speed[p])) for p in group], axis=0),
                )
            ]
        else:  # one constant per stretch, each by its own stations' free flow
            pieces = [
                (n, np.array(io_mean[p]), np.array(dens[p]), free_flow_weight(np.array(speed[p])))
                for n, p in zip(io, group, strict=True)
            ]
        counted = np.sum(
            [anchored_counts(n, m, d, centres, at_s, window_s, w) for n, m, d, w in pieces], axis=0
        )
        return np.asarray(total, dtype=float), counted

    def spans(group: list[tuple[float, float]]) -> tuple[tuple[float, float], ...]:
        inside = [(lo, hi) if hi > lo else (lo, section.length_m) for lo, hi in group]
        return tuple(inside + [(0.0, hi) for lo, hi in group if hi <= lo])

    with_ramp = [side_arcs is None or ramp_between(side_arcs, *pair) for pair in pairs]
    between = [q for q, r in zip(pairs, with_ramp, strict=True) if not r]
    ramps = [q for q, r in zip(pairs, with_ramp, strict=True) if r]
    if record.from_empty and not section.closed and between:
        # Counted since the run's start, when the section was empty: the count itself,
        # unless the density estimate's offset says vehicles depart or arrive inside the
        # stretches and a stretch's count became impossible (``sealed_count``): in a record
        # queued throughout the density estimate alone is off (a signalised arterial).
        io, counted = anchored(between, np.inf)
        mean_count = float(np.nanmean(np.sum([dens[pair] for pair in between], axis=0)))
        tolerance = max(EMPTY_START_TOLERANCE_VEH, EMPTY_START_TOLERANCE * mean_count)
        possible = all(
            sealed_count(times[lo], times[hi], stretch_m((lo, hi), section), section.max_lanes)
            for lo, hi in between
        )
        if abs(float(np.nanmean(counted - io))) <= tolerance or possible:
            pieces["between"] = Piece(spans(between), io)
            pairs = ramps
    # The interval holding each time (the last one before it, past the record's end).
    j = np.clip(np.searchsorted(intervals["begin_s"].to_numpy(), at_s, "right") - 1, 0, None)
    if "between" in pieces:
        # A short stretch with a ramp (the boundary stations' either side of its node):
        # its input-output count drifts at the ramp's flow (a line over a window: SUMO's
        # game/ramp in congestion 3.5 vehicles off on 3), its interval density misses the
        # queue at red and the platoons (drawn arterials: 2.8 and 5.4 vehicles off on 3.8
        # and 4.5 in congestion); its stations' passages projected at their speeds each
        # side of the node follow them (0.25 and 0.31).
        short = [q for q in pairs if stretch_m(q, section) <= SHORT_STRETCH_M]

        # A node nobody turns at (a signal on a crossing street, a ramp nobody used):
        # its stretch's count since the empty start is the count, where it stays possible
        # (``sealed_count``) and within ``EMPTY_START_TOLERANCE_VEH`` of the density
        # estimate in every interval (a slow drift, vehicles turning off at a few per
        # minute, stays possible for minutes but not near the density estimate).
        def sealed(q: tuple[float, float]) -> bool:
            off = np.abs(np.array(dens[q]) - np.array(io_mean[q]))
            near = bool(np.isfinite(off).any()) and float(np.nanmax(off)) <= (
                EMPTY_START_TOLERANCE_VEH
            )
            return near and sealed_count(
                times[q[0]], times[q[1]], stretch_m(q, section), section.max_lanes
            )

        def node_piece(q: tuple[float, float]) -> np.ndarray:
            """Its two stations' passages, each on its side of the node
            (``density.node_projection``)."""
            node = float(side_arcs[(side_arcs > q[0]) & (side_arcs <= q[1])][0])
            e = int(section.edge_index(np.array([node]))[0]) - 1
            line = float(section.offsets_m[e] + section.lengths_m[e])  # where the node begins
            (t_in, v_in), (t_out, v_out) = (own[a][["time_s", "speed_mps"]].T.to_numpy() for a in q)
            metres = (line - q[0], node - line, q[1] - node)
            return node_projection(t_in, v_in, t_out, v_out, at_p, metres)

        closed = [q for q in short if sealed(q)]
        if closed:
            pieces["node_counts"] = Piece(
                spans(closed),
                np.sum(
                    [
                        cumulative_count(times[lo], at_p) - cumulative_count(times[hi], at_p)
                        for lo, hi in closed
                    ],
                    axis=0,
                ),
            )
        short = [q for q in short if q not in closed]
        if short:
            pieces["ramp_nodes"] = Piece(
                spans(short), np.sum([node_piece(q) for q in short], axis=0)
            )
        pairs = [q for q in pairs if q not in short and q not in closed]

    def steady(q: tuple[float, float]) -> bool:
        """Whether the stretch's count up to a constant spans no more than it can hold: a
        count that drifts (a vehicle counted twice, one that parks) does not."""
        lane_m = stretch_m(q, section) * float(section.max_lanes)
        n = cumulative_count(times[q[0]], at_p) - cumulative_count(times[q[1]], at_p)
        return bool(n.size == 0 or np.ptp(n) <= lane_m / JAM_SPACING_M)

    if pairs and side_arcs is not None and record.interval_counts:
        # Interval counts: a stretch with no ramp keeps one constant for the record whatever
        # its neighbours with a ramp need (seeds 300-307, congested, while it was built:
        # 2.07 vehicles per lane off with every stretch on the ramps' line, 1.09 so).
        sealed = [q for q in pairs if q not in ramps and steady(q)]
        if sealed:
            pieces["sealed"] = Piece(spans(sealed), anchored(sealed, np.inf)[1])
        pairs = [q for q in pairs if q not in sealed]
    # Every other stretch is anchored together: each alone takes the density estimate's
    # error on its stretch (a loop on a curve or before a lane drop does not stand for its
    # neighbours), and those errors cancel in their sum, which is all K needs
    # (Spreewaldring: 5.2 vehicles per lane off anchored per stretch, 0.9 together).
    if pairs:
        window_s = IO_ANCHOR_WINDOW_S if ramps else np.inf
        name = "ramps" if "between" in pieces else "stretches"
        pieces[name] = Piece(spans(pairs), anchored(pairs, window_s)[1])
    if ends:
        first, last = own[arcs[0]], own[arcs[-1]]
        down = projected_passages(
            last["time_s"].to_numpy(),
            last["speed_mps"].to_numpy(),
            at_p,
            section.length_m - arcs[-1],
            upstream=False,
        )
        up = projected_passages(
            first["time_s"].to_numpy(), first["speed_mps"].to_numpy(), at_p, arcs[0], True
        )
        w = np.array(up_w)[j]
        pieces["upstream"] = Piece(((0.0, arcs[0]),), w * np.array(up_dens)[j] + (1.0 - w) * up)
        pieces["downstream"] = Piece(((arcs[-1], section.length_m),), down)
    return pieces, pd.DataFrame(rest, columns=["begin_s", "end_s", "vehicles"])


def io_vehicles(
    record: StationRecord, section: Section, run: int, at_s: np.ndarray
) -> tuple[np.ndarray, pd.DataFrame]:
    """Vehicles counted at the times ``at_s`` from the passages (``io_pieces``, summed) and
    the density estimate of the rest of the section per interval."""
    if record.stop_lines:
        side = record.side_arcs if record.side_arcs is not None else np.array([])
        lines = list(record.stop_lines)
        pieces, rest = approach_pieces(
            record.det, section, lines, side, run, at_s, record.near_line
        )
    else:
        pieces, rest = io_pieces(record, section, run, at_s)
    counted = np.zeros(len(at_s))
    for piece in pieces.values():
        counted += piece.vehicles
    return counted, rest


def window_mean(r: pd.DataFrame, column: str, t: float, window_s: float) -> float:
    """Mean of ``column`` over the intervals centred within ``window_s`` / 2 of ``t`` (at
    least the interval holding ``t``)."""
    centre = 0.5 * (r["begin_s"] + r["end_s"])
    m = r[(centre >= t - window_s / 2) & (centre <= t + window_s / 2)]
    if m.empty:
        m = r[(r["begin_s"] <= t) & (r["end_s"] > t)]
    return float(m[column].mean()) if len(m) else float("nan")


def k_estimates(
    traj: pd.DataFrame,
    det_macro: pd.DataFrame,
    section: Section,
    every_s: float,
    window_s: float,
    record: StationRecord | None = None,
) -> pd.DataFrame:
    """Hidden count per snapshot time: the truth, and the estimate from the detectors.

    Estimate: round(vehicles on the section by the detectors) - observed vehicles on it.
    Vehicles by the detectors: the density estimate (``detector_macro``'s) averaged over
    the intervals centred within ``window_s`` of the snapshot (``detectors.k_window_s``; at
    least the interval holding it). Given the stations' ``record`` (loops and their
    passages), the stretches between stations that count every vehicle take the
    input-output count at the snapshot instead, and an open section's end pieces the
    passages projected at their speeds (``io_vehicles``): an interval's mean misses the
    platoons, signal cycles and growing queues within it. With no ramp between two
    stations (``record.side_arcs``) the counts are anchored once for the whole record,
    else (or unknown) by a line over a window.
    With ``record.weight`` (interval counts) the two are blended by it per interval.
    ``k_est_flow_speed``: the former estimate (flow / speed, station cells, interval
    means), for comparison.
    """
    snaps = at_snapshot_times(traj, every_s)
    if record is not None and not (record.det["kind"] == "e1").all():
        record = None  # counts need per-vehicle passages at loops; an E2 reads density only
    if record is not None and "k_point_vpkm" not in record.det:  # else the record's own
        det = record.det.assign(k_point_vpkm=loop_densities(record.det, record.passages))
        record = replace(record, det=det)
    rows = []
    for run, gr in snaps.groupby("run", sort=True):
        r = det_macro[det_macro["run"] == run]
        times = np.sort(gr["time_s"].unique())
        counted, rest = (
            io_vehicles(record, section, run, times)
            if record is not None
            else (np.zeros(len(times)), r)
        )
        if record is not None and record.weight is not None:
            weight = record.weight[record.weight["run"] == run]
        for t, c in zip(times, counted, strict=True):
            g = gr[gr["time_s"] == t]
            vehicles = c + window_mean(rest, "vehicles", t, window_s)
            if record is not None and record.weight is not None:
                w = window_mean(weight, "weight", t, window_s)
                vehicles = w * vehicles + (1.0 - w) * window_mean(r, "vehicles", t, window_s)
            if not np.isfinite(vehicles):
                continue
            n_obs = int(g["observed"].sum())
            k_true = len(g) - n_obs
            k_est = max(0, int(round(vehicles)) - n_obs)
            fs = window_mean(r, "vehicles_flow_speed", t, window_s) if len(r) else np.nan
            rows.append(
                {
                    "run": run,
                    "time_s": t,
                    "n_vehicles": len(g),
                    "n_observed": n_obs,
                    "k_true": k_true,
                    "k_est": k_est,
                    "k_error": k_est - k_true,
                    "k_est_flow_speed": max(0, int(round(fs)) - n_obs) if np.isfinite(fs) else -1,
                }
            )
    return pd.DataFrame(rows, columns=[*K_ESTIMATE_COLUMNS, "k_est_flow_speed"])

"""psi's section speed where vehicles stand between the loops: at a red light or a stop sign.

A loop's speed is that of the vehicles passing it. At a signal the queue stands between the
loops (SUMO stops the first car 1 m before the line, the stop bar's loop 0.5 m before it; a
queue's cars stand with their gaps over the loops upstream), so no loop reads it: on SUMO's
game/cross (40 intervals of 90 s after the warm-up) the loops' count- and cell-weighted
harmonic mean (``section_macro.detector_macro``) read 10.94 m/s where the vehicles' own
mean was 8.41, and the occupancy (k = o / L, q / k) did not see the queue either (10.95).
Edie's generalised definition does: the section's speed is its total distance travelled
over its total time spent, in each interval. The distance: each station's flow over all
its lanes times the arc it stands for (``section_macro.station_cells``). The time: the
vehicles on the section integrated over the interval, as the hidden count reads them from
the stations' passages (the input-output count between stations, ``hidden_count.
io_vehicles``, plus the density estimate of whatever no station pair counts), every
``step_s``: a vehicle standing at red is counted the whole time it stands. game/cross: 8.72
m/s (0.31 mean error per interval, 2.76 before).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import sumolib

from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.density import SPEED_FLOW_ABOVE_MPS
from macromicro_sumo.truth.hidden_count import io_vehicles
from macromicro_sumo.truth.section_detectors import STOP_NODE_TYPES
from macromicro_sumo.truth.section_macro import loop_densities, station_cells
from macromicro_sumo.truth.stations import (
    StationRecord,
    full_stations,
    station_passages,
    station_speeds,
)


def stop_line_edges(section: Section, net: sumolib.net.Net) -> list[str]:
    """The section's edges that end at a node where vehicles stand at the stop line (a
    signal or a stop sign: ``section_detectors.STOP_NODE_TYPES``)."""
    return [e for e in section.edge_ids if net.getEdge(e).getToNode().getType() in STOP_NODE_TYPES]


def station_flows(
    d: pd.DataFrame, passages: pd.DataFrame, section: Section, begins: np.ndarray, ends: np.ndarray
) -> dict[float, np.ndarray]:
    """{station arc: its flow over all its lanes (veh/s) in each [begin, end)}: a station
    with a loop on every lane (``stations.full_stations``) counts its passages as the
    input-output count does, a vehicle that changes lane over its loops once
    (``stations.station_passages``); another its loops' mean flow times its edge's
    lanes."""
    lap_s = section.length_m / (1.5 * float(np.nanmax(section.limits_mps)))
    full = set(full_stations(d, section).tolist())
    out = {}
    for arc, g in d[d["kind"] == "e1"].groupby("arc_m"):
        if float(arc) in full:
            t = station_passages(d, passages, float(arc), lap_s)["time_s"].to_numpy()
            t = np.sort(t)
            n = np.searchsorted(t, ends, "left") - np.searchsorted(t, begins, "left")
            out[float(arc)] = n / (ends - begins)
        else:
            lanes = int(section.n_lanes[section.edge_index(np.array([arc]))[0]])
            per = g.groupby("begin_s")["flow_vph"].mean() / 3600.0 * lanes
            out[float(arc)] = per.reindex(begins).to_numpy(dtype=float)
    return out


def edie_speeds(
    det_macro: pd.DataFrame, record: StationRecord, section: Section, step_s: float
) -> pd.DataFrame:
    """``det_macro`` (``section_macro.detector_macro``) with the ``mean_speed_mps`` of each
    interval in which a station's speed (``stations.station_speeds``: 0 where nobody
    passed) is below ``density.SPEED_FLOW_ABOVE_MPS`` the section's total distance over its
    total time (the module's docstring); unchanged where the stations give no count (E2
    detectors, no passages) or the interval no distance or no vehicle. Where every station
    flows, every vehicle passes the loops and their speeds are the better reading: the
    count's and the flows' noise within an interval is larger (SUMO's game/corridor, free
    flow: 0.015 m/s mean error per interval against 0.075; netgen_corridor 0.07 against
    0.16). Meant for sections with a stop line (``stop_line_edges``)."""
    det = record.det
    if det.empty or not (det["kind"] == "e1").all() or record.passages.empty:
        return det_macro
    record = replace(record, det=det.assign(k_point_vpkm=loop_densities(det, record.passages)))
    stations = np.sort(det["arc_m"].unique())
    cells = dict(zip(stations, station_cells(stations, section), strict=True))
    out = det_macro.copy()
    speeds = out["mean_speed_mps"].to_numpy(dtype=float).copy()
    for run, rows in out.groupby("run", sort=True):
        d = det[det["run"] == run]
        spans = rows[["begin_s", "end_s"]].to_numpy(dtype=float)
        flows = station_flows(d, record.passages[record.passages["run"] == run], section, *spans.T)
        # Vehicle-metres per second in each interval: each station's flow over its arc.
        distance = np.nansum([q * cells[a] for a, q in flows.items()], axis=0)
        times = [np.arange(b + step_s / 2, e, step_s) for b, e in spans]
        counted, rest = io_vehicles(record, section, int(run), np.concatenate(times))
        rest_by_begin = dict(zip(rest["begin_s"].round(6), rest["vehicles"], strict=True))
        start = 0
        for i, (idx, (b, _), t) in enumerate(zip(rows.index, spans, times, strict=True)):
            on = counted[start : start + len(t)]
            start += len(t)
            if not len(t):
                continue
            e1 = d[(d["begin_s"] == b) & (d["kind"] == "e1")]
            if float(station_speeds(e1).min()) >= SPEED_FLOW_ABOVE_MPS:
                continue  # every station flows: the loops' speeds (no standing vehicle)
            vehicles = float(on.mean()) + float(rest_by_begin.get(round(b, 6), 0.0))
            if vehicles > 0 and distance[i] > 0:  # NaN (no density estimate of the rest): kept
                speeds[out.index.get_loc(idx)] = distance[i] / vehicles
    out["mean_speed_mps"] = speeds
    return out

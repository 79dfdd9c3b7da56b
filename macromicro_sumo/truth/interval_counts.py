"""The hidden count from the stations' interval counts alone (field data: no per-vehicle
passages), by conservation between stations.

A station that counts every lane gives, interval by interval, how many vehicles crossed it:
the count between two such stations changes by those in less those out, so it is known up
to a constant at each interval's bounds, and between them (vehicles assumed evenly spread
over an interval) by the line through them. The interval density estimate alone misses a
queue's growth and a stop-and-go wave between stations; the counts do not. The constant is
the density estimate's, weighted to free-flowing intervals (``hidden_count.io_pieces``):
one for the record where no ramp lies between the stations, a line over a window where one
does. The counts take over from the density estimate where the slowest station's interval
speed falls from ``QUEUE_BLEND_MPS[1]`` to ``QUEUE_BLEND_MPS[0]`` (free flow keeps the
density estimate, which the constant carries no better there). The end pieces beyond the
outermost stations and a short stretch around a ramp's node (its count drifts at the
ramp's flow within an interval) keep the density estimate; occupancy is divided by the
run's effective vehicle length (``effective_densities``), as no passage tells the lengths.

At signals (a section with a stop line) the approaches are counted from the signals'
programs instead (``signal_counts``): spread evenly, a stop-line loop's count is timed by
the cycle within its interval (with stop lines allowed here, the bench's arterials 1, 2,
600-603 went from 4.09 / 6.62 vehicles per lane, free / congested, to 4.32 / 9.32).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import sumolib

from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.density import (
    DEFAULT_VEHICLE_LENGTH_M,
    occupancy_weight,
    point_density,
)
from macromicro_sumo.truth.section_macro import run_vehicle_lengths
from macromicro_sumo.truth.section_speed import stop_line_edges
from macromicro_sumo.truth.signal_counts import approaches
from macromicro_sumo.truth.signal_lines import stop_lines
from macromicro_sumo.truth.stations import (
    StationRecord,
    full_stations,
    side_junction_arcs,
    station_speeds,
)

QUEUE_BLEND_MPS = (10.0, 15.0)
"""The slowest station's interval speed (m/s) at or below which the interval counts' estimate
is taken, at or above which the density estimate alone; linear in between. Per lane free /
congested on seeds 200-207 and 300-307 (scripts/bench_hidden_count.py): 0.89 / 1.24 and
0.92 / 1.08; with (5, 10) 0.89 / 1.31 and 0.94 / 1.18; with (8, 12) 0.92 / 1.26 and
0.92 / 1.15."""


def interval_passages(det: pd.DataFrame) -> pd.DataFrame:
    """Passages (``run, detector_id, time_s, vehicle_id, speed_mps, length_m``) made from the
    E1 stations' interval counts: per station (its lanes' ``n_veh`` summed), the cumulative
    count linear within each interval, one passage where it crosses each k + 1/2. A
    station's passages go to its first loop's instantaneous ID (``i_`` + ID), at the
    station's interval speed, with SUMO's passenger car's length."""
    rows = []
    e1 = det[det["kind"] == "e1"]
    for (run, arc), g in e1.groupby(["run", "arc_m"], sort=True):
        per = g.groupby(["begin_s", "end_s"], sort=True)
        n = per["n_veh"].sum().to_numpy(dtype=float)
        bounds = per.size().index.to_frame(index=False)
        begin, end = bounds["begin_s"].to_numpy(float), bounds["end_s"].to_numpy(float)
        speed = np.array([float(station_speeds(x).iloc[0]) for _, x in per])
        cum = np.concatenate([[0.0], np.cumsum(n)])
        k = np.arange(int(np.floor(cum[-1] + 0.5))) + 0.5  # the crossings' levels
        j = np.clip(np.searchsorted(cum, k, side="right") - 1, 0, len(n) - 1)
        frac = (k - cum[j]) / np.where(n[j] > 0, n[j], 1.0)
        first = str(g.sort_values("lane_index")["detector_id"].iloc[0])
        rows.append(
            pd.DataFrame(
                {
                    "run": run,
                    "detector_id": f"i_{first}",
                    "time_s": begin[j] + frac * (end[j] - begin[j]),
                    "vehicle_id": [f"{run}:{arc}:{i}" for i in range(len(k))],
                    "speed_mps": speed[j],
                    "length_m": DEFAULT_VEHICLE_LENGTH_M,
                }
            )
        )
    columns = ["run", "detector_id", "time_s", "vehicle_id", "speed_mps", "length_m"]
    return pd.concat(rows, ignore_index=True)[columns] if rows else pd.DataFrame(columns=columns)


def queued_weight(det: pd.DataFrame) -> pd.DataFrame:
    """Per run and interval (``run, begin_s, end_s, weight``) the interval counts' weight
    against the density estimate: the slowest station's speed through ``QUEUE_BLEND_MPS``
    (a station nobody crossed counts as standing)."""
    rows = []
    for (run, begin, end), g in det[det["kind"] == "e1"].groupby(["run", "begin_s", "end_s"]):
        ws = occupancy_weight(station_speeds(g).to_numpy(dtype=float), *QUEUE_BLEND_MPS)
        w = float(ws.max())
        rows.append({"run": run, "begin_s": begin, "end_s": end, "weight": w})
    return pd.DataFrame(rows, columns=["run", "begin_s", "end_s", "weight"])


def effective_densities(det: pd.DataFrame) -> np.ndarray:
    """Each E1 row's density (``density.point_density``) with the run's effective vehicle
    length: the median over its loops of theirs (``density.effective_length_m``), as no
    passage tells the lengths; SUMO's passenger car where no loop flowed freely. Per loop
    one with lane changes over it reads long (14.6 m against its passages' 6.3 on drawn
    seed 210's entry); on seeds 200-207, per lane free / congested 0.89 / 1.24 with the
    run's median, 0.86 / 1.29 per loop, 1.05 / 1.31 with a 5 m car."""
    cols = ["flow_vph", "speed_mps", "occupancy_pct"]
    return point_density(*(det[c].to_numpy(dtype=float) for c in cols), run_vehicle_lengths(det))


def complete_counts(det: pd.DataFrame) -> bool:
    """Whether every E1 loop has a finite count in every interval of its run and the
    intervals follow each other without a gap: else a station's cumulative count misses
    vehicles and the counts between stations drift."""
    if det.empty or not (det["kind"] == "e1").all() or not np.isfinite(det["n_veh"]).all():
        return False
    for _, d in det.groupby("run"):
        spans = d[["begin_s", "end_s"]].drop_duplicates().sort_values("begin_s").to_numpy()
        if len(d) != len(spans) * d["detector_id"].nunique():
            return False
        if len(spans) > 1 and not np.allclose(spans[1:, 0], spans[:-1, 1]):
            return False
    return True


def interval_record(
    det: pd.DataFrame,
    section: Section,
    net: sumolib.net.Net,
    net_file: Path | None = None,
    near_line: bool | str = False,
) -> StationRecord | None:
    """The stations' record for ``hidden_count.k_estimates`` from their interval counts
    alone (``interval_passages``, ramps from ``net``, weighted by ``queued_weight``), or None
    (the density estimate alone) where fewer than two stations count every lane or a count
    is missing. Where the section has a stop line: its signals' programs from ``net_file``
    (``signal_counts.stop_lines``), the approaches to them counted by conservation
    (``signal_counts.approach_pieces``); None where ``net_file`` is not given, a stop line
    has no fixed-time signal (a stop sign) or no approach has its two stations.
    ``near_line``: ``StationRecord.near_line``."""
    if section.closed or not complete_counts(det):
        return None
    if any(len(full_stations(d, section)) < 2 for _, d in det.groupby("run")):
        return None
    det = det.assign(k_point_vpkm=effective_densities(det))
    side = side_junction_arcs(net, section)
    if stop_line_edges(section, net):
        if net_file is None:
            return None
        lines = stop_lines(net_file, section)
        if len(lines) != len(stop_line_edges(section, net)) or not any(
            approaches(d, section, lines, side) for _, d in det.groupby("run")
        ):
            return None
        return StationRecord(
            det,
            pd.DataFrame(),
            side,
            interval_counts=True,
            stop_lines=tuple(lines),
            near_line=near_line,
        )
    return StationRecord(
        det,
        interval_passages(det),
        side,
        interval_counts=True,
        weight=queued_weight(det),
    )

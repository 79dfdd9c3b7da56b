"""The stations of a section's detectors and what they recorded, for counting the vehicles
between them (``hidden_count``): which stations count every vehicle, where ramps join, each
station's passages and interval speeds, and the record ``hidden_count.k_estimates`` reads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import sumolib

from macromicro_sumo.road.section import Section

PASSAGE_LAG_STEPS = 1
"""SUMO's instantaneous loops time a crossing one step before the recorded state that shows
it (trajectories.csv labels the state after a step with that step's end): a vehicle
reported at 300.48 s is at 535.7 m at 300.5 s and 545.9 m at 301.0 s over a loop at
545.4 m (step 0.5 s). Counted at a snapshot without this lag, every station boundary is
off by the vehicles crossing it within a step; on the bench the counted stretches were
0.9-1.1 vehicles off with it ignored, 0.1-0.15 with it (docs/sections.md, "Hidden
count")."""


def stretch_m(pair: tuple[float, float], section: Section) -> float:
    """Arc length from station ``pair[0]`` to ``pair[1]`` (around the loop where it closes)."""
    lo, hi = pair
    return hi - lo if hi > lo else hi + section.length_m - lo


def full_stations(det: pd.DataFrame, section: Section) -> np.ndarray:
    """Arcs of the E1 stations that count every vehicle crossing them: a loop on every lane
    of their edge (each E1 loop has its instantaneous loop beside it, whose passages are
    the counts; a lane nobody used has none). Only between two such stations is the
    input-output count a count."""
    e1 = det[det["kind"] == "e1"]
    arcs = [
        float(arc)
        for arc, g in e1.groupby("arc_m")
        if g["lane_index"].nunique() == int(section.n_lanes[section.edge_index(np.array([arc]))[0]])
    ]
    return np.array(sorted(arcs))


def side_junction_arcs(net: sumolib.net.Net, section: Section) -> np.ndarray:
    """Arcs of the section's inner nodes where an edge off the section joins or leaves (a
    ramp), from the SUMO network (sumolib's ``Net``): only a stretch holding one of them
    lets vehicles in or out between its stations."""
    ids = set(section.edge_ids)
    arcs = []
    for e, eid in enumerate(section.edge_ids):
        if e == 0 and not section.closed:
            continue  # the section's entry is an end piece, never between two stations
        node = net.getEdge(eid).getFromNode()
        edges = [*node.getIncoming(), *node.getOutgoing()]
        if any(x.getID() not in ids for x in edges):
            arcs.append(float(section.offsets_m[e]))
    return np.array(arcs)


def ramp_between(side_arcs: np.ndarray, lo: float, hi: float) -> bool:
    """Whether a ramp joins or leaves between the stations at ``lo`` and ``hi`` (``hi`` <
    ``lo``: the stretch that closes a loop)."""
    if hi < lo:
        return bool(((side_arcs > lo) | (side_arcs <= hi)).any())
    return bool(((side_arcs > lo) & (side_arcs <= hi)).any())


def station_passages(d: pd.DataFrame, p: pd.DataFrame, arc: float, within_s: float) -> pd.DataFrame:
    """A station's passages (time, speed) in time order, a vehicle seen again within
    ``within_s`` once: one that changes lane over the loops is seen by two of them (SUMO's
    loops report its ID; a field station pairs its lanes by time), and a double count
    makes input-output counts drift for good. ``within_s``: shorter than the fastest lap of
    a closed section, on which a vehicle passes again each lap."""
    own = set(d.loc[d["arc_m"] == arc, "detector_id"])
    q = p[p["detector_id"].str.removeprefix("i_").isin(own)].sort_values(["vehicle_id", "time_s"])
    again = (q["vehicle_id"] == q["vehicle_id"].shift()) & (
        q["time_s"] - q["time_s"].shift() < within_s
    )
    return q[~again].sort_values("time_s")[["time_s", "speed_mps"]]


def station_speeds(e1: pd.DataFrame) -> pd.Series:
    """Each station's interval speed (harmonic over its lanes' passages; 0 where nobody
    passed: a standing queue)."""
    n, v = e1["n_veh"].to_numpy(dtype=float), e1["speed_mps"].to_numpy(dtype=float)
    ok = (n > 0) & np.isfinite(v) & (v > 0)
    inv = pd.Series(np.where(ok, n / np.where(ok, v, 1.0), 0.0)).groupby(e1["arc_m"].to_numpy())
    cnt = pd.Series(np.where(ok, n, 0.0)).groupby(e1["arc_m"].to_numpy())
    return (cnt.sum() / inv.sum()).fillna(0.0)


STOP_BAR_M = 0.5
"""How far before a section edge's end at a signal or a stop sign the tool's boundary
station sits (``section_detectors.boundary_arcs``): SUMO stops a car at red 1 m before the
lane's end, so the queue stands on a counted stretch (15 m before the line, between them,
it was the density estimate's: game/cross K 1.35 vehicles per lane off in congestion)."""


@dataclass(frozen=True)
class Piece:
    """A part of the section and its vehicles counted at each snapshot time."""

    arcs_m: tuple[tuple[float, float], ...]  # [lo, hi) ranges of arc it covers
    vehicles: np.ndarray  # (snapshot times,)


@dataclass(frozen=True)
class StationRecord:
    """What the detectors recorded for counting, and how to read it.

    ``det``: the detector table (E1 loops only); ``passages``: their per-vehicle passages.
    ``side_arcs`` (``side_junction_arcs``): where ramps join or leave; None: unknown, every
    stretch may hold one. ``passage_lag_s``: how far the passages' clock runs behind the
    snapshot times (a SUMO run: ``PASSAGE_LAG_STEPS`` steps). ``from_empty``: the passages
    start with the section empty (a simulation from its first step). ``interval_counts``:
    the passages are the stations' interval counts spread over their intervals
    (``interval_counts.interval_passages``): the end pieces are left to the density
    estimate. ``weight``: per interval (``run, begin_s, end_s, weight``) the counted
    estimate's weight against the density estimate alone; None: the counted one only.
    ``stop_lines`` (``signal_counts.StopLine``): with interval counts, the signals' programs;
    the approaches to them are counted by ``signal_counts.approach_pieces`` instead;
    ``near_line``: with the near-line loops' standing queue where no station reads one, or
    "all": a share of it on every approach (``signal_counts.approach_count``).
    """

    det: pd.DataFrame
    passages: pd.DataFrame
    side_arcs: np.ndarray | None = None
    passage_lag_s: float = 0.0
    from_empty: bool = False
    interval_counts: bool = False
    weight: pd.DataFrame | None = None
    stop_lines: tuple = ()
    near_line: bool | str = False

"""When within an interval a stop line's vehicles pass it (opt-in, ``TIMING``): the red's
queue first, at the saturation flow, then the arrivals at their own flow
(``front_fraction``; ``signal_counts.cumulative`` with ``front``), instead of evenly over
the passing seconds. A station past the line sees the same departures a crossing later
(``signal_counts.station_front``). With ``front_junctions`` the junction stretch between
them is counted too: the vehicles that reach that station within the crossing
(``junction_counts``), in place of its interval density.

A measured no as a default (docs/sections-log.md, "Front-loaded departures at signals,
and the io mean over the whole interval (stop 51, hH51)"): on drawn signalised arterials it
beats ``near_line = "station"`` alone but not the default everywhere.
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.truth.signal_lines import StopLine

SATURATION_HEADWAY_S = 2.0
"""Seconds between two vehicles of a lane leaving a standing queue at green (SUMO's Krauss
cars: about 1.8-2.2 s)."""

STEP_S = 0.5
"""The grid on which an interval's departure rate is integrated."""

TIMING = "even"
"""``even``: a stop line's count spread evenly over its passing seconds (the default);
``front``: front-loaded (``front_fraction``) at the stop bar and a crossing later at the
station past the line; ``front_junctions``: the same, with the junction stretches counted
(``junction_counts.junction_pieces``, ``hidden_count.io_vehicles``)."""

IO_MEAN_EXACT = False
"""``signal_counts.density_constant``: the mean of the counts' ``io`` over the interval at 1 s
midpoints (True) instead of at 7 points with both ends (a 90 s interval over a 90 s cycle
counts one phase twice: docs/sections-log.md, stop 47, hQ47)."""


def front_fraction(
    line: StopLine,
    begin: float,
    end: float,
    flow_vps: float,
    lanes: int,
    t: np.ndarray,
    delay_s: float = 0.0,
) -> np.ndarray | None:
    """The share of the interval [``begin``, ``end``)'s count over ``lanes`` lanes that has
    passed by ``t``, the line's program ``delay_s`` later: while the line lets pass, the
    queue of the red before (its arrivals at the mean flow ``flow_vps``, vehicles per
    second over the lanes) leaves at the saturation flow, then the arrivals at that flow;
    None where the line never lets pass within it (the caller keeps its own spread)."""
    m = max(int(round((end - begin) / STEP_S)), 1)
    edges = np.linspace(begin, end, m + 1) - delay_s
    passing = np.diff(line.green_s(edges)) / np.diff(edges)
    cycle = float(np.sum(line.durations_s))
    starts = line.green_starts(edges[0] - 2.0 * cycle, edges[-1] + STEP_S)
    if not starts or passing.sum() <= 0:
        return None
    s_at, reds = np.array(starts).T
    mid = 0.5 * (edges[1:] + edges[:-1])
    k = np.searchsorted(s_at, mid, side="right") - 1
    since = np.where(k >= 0, mid - s_at[np.maximum(k, 0)], np.inf)
    red = np.where(k >= 0, reds[np.maximum(k, 0)], 0.0)
    sat = 1.0 / SATURATION_HEADWAY_S
    lam = flow_vps / max(lanes, 1)
    queue_s = np.where(sat > lam, lam * red / max(sat - lam, 1e-9), np.inf)
    rate = passing * np.where(since < queue_s, sat, lam)
    cum = np.concatenate([[0.0], np.cumsum(rate)])
    if cum[-1] <= 0:
        return None
    return np.interp(np.asarray(t, dtype=float), edges + delay_s, cum / cum[-1])

"""The recorded signals of a section (``signals.csv``, ``truth.signals``) as the stages read
them: the red and yellow stop lines at each snapshot (the envs' standing leaders) and the
signals' settings to restore in SUMO."""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.sumo.states import STOP_STATES

# signals.csv: per recorded step and signalised link of each lane of a section edge with a
# link onto the next section edge (the lane's own links: ``truth.signals``), the signal's
# program, phase and seconds left in it, and the link's stop line (lane index, arc: its
# edge's end) with its state letter.
SIGNAL_COLUMNS = (
    "run", "time_s", "signal_id", "program", "phase", "left_s", "lane_index", "arc_m", "state"
)  # fmt: skip


def _signal_groups(signals: pd.DataFrame | None) -> dict[tuple[int, float], pd.DataFrame]:
    if signals is None or signals.empty:
        return {}
    key = [signals["run"].astype(int), signals["time_s"].round(6)]
    return {(int(r), float(t)): g for (r, t), g in signals.groupby(key, sort=False)}


def signal_stops(
    signals: pd.DataFrame | None, runs: np.ndarray, times_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """(lane, arc) (S, P) of the stop lines whose signal shows red or yellow
    (``sumo.states.STOP_STATES``: what a driver treats as a standing leader there, as
    the envs and the deployment do) at each (run, time); NaN arc: padding. None: no signal."""
    groups = _signal_groups(signals)
    if not groups:
        return None
    stops = []
    for r, t in zip(runs, times_s, strict=True):
        g = groups.get((int(r), round(float(t), 6)))
        red = g[g["state"].isin(list(STOP_STATES))] if g is not None else None
        pts = set() if red is None else set(zip(red["lane_index"], red["arc_m"], strict=True))
        stops.append(sorted(pts))
    p = max(1, max(len(x) for x in stops))
    lane, arc = np.zeros((len(stops), p), dtype=np.int64), np.full((len(stops), p), np.nan)
    for i, pts in enumerate(stops):
        for j, (ln, a) in enumerate(pts):
            lane[i, j], arc[i, j] = int(ln), float(a)
    return lane, arc


def signal_settings(
    signals: pd.DataFrame | None, runs: np.ndarray, times_s: np.ndarray
) -> np.ndarray | None:
    """(S,) object array: at each (run, time) the section's signals as recorded, a tuple of
    (signal ID, program, phase index, seconds left in the phase) (``Simulation.
    set_signal_states``); an empty tuple where nothing was recorded then. None: no signal."""
    groups = _signal_groups(signals)
    if not groups:
        return None
    out = np.empty(len(runs), dtype=object)
    for i, (r, t) in enumerate(zip(runs, times_s, strict=True)):
        g = groups.get((int(r), round(float(t), 6)))
        if g is None:
            out[i] = ()
            continue
        rows = g.drop_duplicates("signal_id")[["signal_id", "program", "phase", "left_s"]]
        out[i] = tuple((str(a), str(b), int(c), float(d)) for a, b, c, d in rows.itertuples(False))
    return out

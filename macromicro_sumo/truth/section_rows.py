"""The trajectory rows ``truth.section.record_run`` collects: every vehicle on the section
at every recorded step, in section coordinates (edge, lane index, arc), sorted by time,
lane and arc.

Each step keeps SUMO's read of the road (``VehicleStates``: its arrays, not copies; nobody
writes to them) and the steps are filtered to the section's lanes together, in a few
C-level passes, at every ``flush`` (the memory check's steps), at the end, and where
the steps kept hold ``PENDING_ROWS`` vehicles (~160 B each: the ID and lane strings, three
floats), so that a large network around a short section does not keep hundreds of MB. A
filter per step cost ~20 us of numpy and Python calls a step on Bremen, for ~42 rows.
"""

from __future__ import annotations

from itertools import chain, compress, repeat
from typing import Any

import numpy as np

from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.states import VehicleStates

_STATES = ("pos_m", "speed_mps", "accel_mps2")
PENDING_ROWS = 200_000


class SectionRows:
    """The section's rows of the steps ``add`` has been given."""

    def __init__(self, section: Section) -> None:
        # section.lanes as codes into one array: (edge, lane index, arc at lane start, scale).
        self.lane_code = {lane: i for i, lane in enumerate(section.lanes)}
        self.lane_rows = np.array(list(section.lanes.values()), dtype=float).reshape(-1, 4)
        self.pending: list[VehicleStates] = []
        self.pending_rows = 0
        self.pending_times: list[float] = []
        self.times: list[float] = []
        self.counts: list[int] = []  # rows of each step in ``times`` (0: nobody on it)
        self.vids: list[str] = []
        self.chunks: dict[str, list[np.ndarray]] = {k: [] for k in ("lane_code", *_STATES)}

    def add(self, time_s: float, st: VehicleStates) -> None:
        """The step at ``time_s`` (s), whose vehicles ``st`` holds."""
        if st.ids:
            self.pending.append(st)
            self.pending_times.append(time_s)
            self.pending_rows += len(st.ids)
            if self.pending_rows >= PENDING_ROWS:
                self.flush()

    def flush(self) -> int:
        """Filter the steps added since the last flush; the rows so far."""
        if not self.pending:
            return len(self.vids)
        sizes = [len(st.ids) for st in self.pending]
        lanes = chain.from_iterable(st.lanes for st in self.pending)
        code = np.fromiter(map(self.lane_code.get, lanes, repeat(-1)), np.int64, sum(sizes))
        on = code >= 0
        ids = chain.from_iterable(st.ids for st in self.pending)
        self.vids.extend(compress(ids, on.tolist()))
        step = np.repeat(np.arange(len(sizes)), sizes)
        self.counts.extend(np.bincount(step[on], minlength=len(sizes)).tolist())
        self.times.extend(self.pending_times)
        self.chunks["lane_code"].append(code[on])
        for name in _STATES:
            self.chunks[name].append(np.concatenate([getattr(st, name) for st in self.pending])[on])
        self.pending.clear()
        self.pending_times.clear()
        self.pending_rows = 0
        return len(self.vids)

    def columns(self) -> tuple[dict[str, Any], list[str]]:
        """(time_s, lane_index, edge_index, arc_m, speed_mps, accel_mps2 columns; the
        vehicle of each row), sorted by time, lane and arc (stable: SUMO's order on ties)."""
        if not self.flush():  # nobody on the section: the empty columns as ever
            empty = ("time_s", "lane_index", "edge_index", "arc_m", "speed_mps", "accel_mps2")
            return {k: [] for k in empty}, []
        cols: dict[str, Any] = {k: np.concatenate(v) for k, v in self.chunks.items()}
        where = self.lane_rows[cols.pop("lane_code")]
        step = np.repeat(np.arange(len(self.counts)), self.counts)
        cols = {
            "time_s": np.repeat(np.array(self.times, dtype=float), self.counts),
            "lane_index": where[:, 1].astype(np.int64),
            "edge_index": where[:, 0].astype(np.int64),
            "arc_m": where[:, 2] + cols.pop("pos_m") * where[:, 3],
            **cols,
        }
        # np.lexsort((arc, lane, step)), what pandas' stable sort_values by time, lane and
        # arc gave, as two stable argsorts: the arcs, then (step, lane) as one integer.
        order = np.argsort(cols["arc_m"], kind="stable")
        key = step * (int(cols["lane_index"].max()) + 1) + cols["lane_index"]
        order = order[np.argsort(key[order], kind="stable")]
        vids = np.array(self.vids, dtype=object)[order].tolist()
        return {k: v[order] for k, v in cols.items()}, vids

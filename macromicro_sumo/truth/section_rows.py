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
import pandas as pd

from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.states import VehicleStates

_STATES = ("pos_m", "speed_mps", "accel_mps2")
_COLUMNS = ("time_s", "lane_index", "edge_index", "arc_m", "speed_mps", "accel_mps2")
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
            return {k: [] for k in _COLUMNS}, []
        cols, order = self._sorted()
        return cols, np.array(self.vids, dtype=object)[order].tolist()

    def _sorted(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """(``columns``' columns, sorted; the order of ``self.vids`` that sorts them), the
        rows flushed and not none."""
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
        # arc gave, as one stable argsort of (step, lane, the arc's rank) as one integer:
        # equal ranks are equal arcs (NaN one rank, last, as lexsort puts it), ties keep
        # SUMO's order. A third of the time of a stable argsort of the float arcs.
        _, rank = np.unique(cols["arc_m"], return_inverse=True)
        key = step * (int(cols["lane_index"].max()) + 1) + cols["lane_index"]
        order = np.argsort(key * (int(rank.max()) + 1) + rank, kind="stable")
        return {k: v[order] for k, v in cols.items()}, order

    def frame(
        self, run: int, types: dict[str, str], observed: dict[str, bool]
    ) -> tuple[pd.DataFrame, int, int]:
        """(run ``run``'s trajectory frame, the vehicles in it, the observed ones among
        them); ``types`` and ``observed``: each vehicle's vType and whether it is observed."""
        if not self.flush():
            return self._frame_by_row(run, types, observed)
        # Per vehicle, not per row: the IDs as codes into their first appearances, each
        # column a take of the vehicles' values (a string column from the few IDs, as pandas
        # reads a list of them), the same frame in half the time.
        codes, first = pd.factorize(np.array(self.vids, dtype=object))
        if not all(v in types for v in first):
            return self._frame_by_row(run, types, observed)
        cols, order = self._sorted()
        codes = codes[order]
        obs = np.array([observed.get(v, True) for v in first], dtype=bool)
        df = pd.DataFrame(
            {"time_s": cols.pop("time_s"), "vehicle_id": _texts(first, codes), **cols}
        )
        df.insert(0, "run", run)
        df.insert(3, "vtype", _texts([types[v] for v in first], codes))
        df.insert(4, "observed", obs[codes])
        return df, len(first), int(obs.sum())

    def _frame_by_row(
        self, run: int, types: dict[str, str], observed: dict[str, bool]
    ) -> tuple[pd.DataFrame, int, int]:
        """``frame`` a row at a time: where nobody was on the section or a vehicle has no
        vType (NaN there, as Series.map gave)."""
        cols, vids = self.columns()
        df = pd.DataFrame({"time_s": cols.pop("time_s"), "vehicle_id": vids, **cols})
        df.insert(0, "run", run)
        # Dict look-ups, not Series.map (a tenth of the time on pandas 3's strings); where a
        # vehicle were missing, what map gave: NaN, and NaN as a bool (True).
        vtype = [types.get(v, np.nan) for v in vids] if vids else df["vehicle_id"].map(types)
        df.insert(3, "vtype", vtype)
        df.insert(
            4, "observed", np.fromiter(map(observed.get, vids, repeat(True)), bool, len(vids))
        )
        seen = int(df["vehicle_id"].nunique())
        return df, seen, int(df.loc[df["observed"], "vehicle_id"].nunique())


def _texts(values: Any, codes: np.ndarray) -> Any:
    """The column of ``values[codes]``, with the dtype pandas gives a list of ``values``."""
    return pd.Series(list(values)).array.take(codes)

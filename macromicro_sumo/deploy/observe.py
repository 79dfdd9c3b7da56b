"""What a deployment's driven vehicle on a section sees, from SUMO's state read once per
step (``sumo.simulation.VehicleStates``): the section env's observation
(``env.section_bank.section_observations``) with SUMO's own leader, and what the safety
layer needs (``deploy.drivers.safety_cap``). Vectorised over the driven vehicles: per
vehicle only dictionary look-ups in Python.
"""

from __future__ import annotations

from itertools import repeat

import numpy as np

from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section
from macromicro_sumo.sumo.simulation import VehicleStates

STOP_DECEL_MPS2 = 9.0  # a standing "leader" (stop line, lane end) never brakes: any value
STANDING = (0.0, 0.0, STOP_DECEL_MPS2)  # (length, minGap, decel) of a standing leader


class Table:
    """Rows of a small table looked up by key with numpy: each key holds the code of a
    row, the rows are one array; a key not in it gets row 0, ``missing`` (a list of
    tuples made an array costs ~0.45 us a row, the codes and a take ~0.1: measured)."""

    def __init__(self, missing: tuple[float, ...]) -> None:
        self.code: dict[str, int] = {}
        self.rows: list[tuple[float, ...]] = [missing]
        self.array = np.array(self.rows, dtype=float)

    @classmethod
    def of_rows(cls, rows: dict[str, tuple], missing: tuple[float, ...]) -> Table:
        """A table with a row per key."""
        table = cls(missing)
        table.code = {key: i + 1 for i, key in enumerate(rows)}
        table.rows += list(rows.values())
        table.array = np.array(table.rows, dtype=float)
        return table

    def add_row(self, row: tuple) -> int:
        """A new row; its code."""
        self.rows.append(row)
        self.array = np.array(self.rows, dtype=float)
        return len(self.rows) - 1

    def of(self, keys: list[str]) -> np.ndarray:
        """(len(keys), width) rows; a missing key's is the ``missing`` row."""
        codes = np.fromiter(map(self.code.get, keys, repeat(0)), np.int64, len(keys))
        return self.array[codes]


def observe_rows(
    sec: Section,
    lanes: Table,
    observation: str,
    vids: list[str],
    rows: np.ndarray,
    st: VehicleStates,
    leaders: list[tuple[str, float]],
    shapes: Table,
    stop_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Observations (V, obs_dim) of driven vehicles ``vids`` (rows ``rows`` of ``st``), as
    the section env defines them, the leader SUMO's (``leaders``: ``Simulation.leaders``):
    front-to-front spacing = SUMO's gap + own minGap + leader's length; ``stop_m``: the
    distance from each front to a red light or the end of a lane the vehicle must leave
    (inf: none), a standing leader there when nearer than the leader (its back at the
    line, a vehicle length long). ``lanes``: ``section.lanes`` as a ``Table``; ``shapes``:
    vehicle -> (length, minGap, decel), ``STANDING`` where missing.
    Also returns SUMO's gap to what the vehicle sees ahead, that leader's decel, and its
    index in ``vids`` where it is a driven vehicle (-1: none, not driven, or a standing
    leader): the safety layer knows a driven leader's next speed, its command."""
    n = len(vids)
    pos, speed = st.pos_m[rows], st.speed_mps[rows]
    where = lanes.of([st.lanes[i] for i in rows.tolist()])
    edge, lane = where[:, 0].astype(np.int64), where[:, 1].astype(np.int64)
    arc = where[:, 2] + pos * where[:, 3]
    own = shapes.of(vids)
    length, min_gap = own[:, 0], own[:, 1]
    # The leader SUMO sees, if it is on the road (in ``st``).
    lead_ids = [lid for lid, _ in leaders]
    lead_row = np.fromiter(map(st.index.get, lead_ids, repeat(-1)), np.int64, n)
    has = lead_row >= 0
    gap = np.fromiter((g for _, g in leaders), float, n)
    lead_shape = np.where(has[:, None], shapes.of(lead_ids), STANDING)
    lead_speed = np.where(has, st.speed_mps[lead_row], 0.0)
    s = gap + min_gap + lead_shape[:, 0]
    ok = has & (s < NO_LEADER_GAP_M)
    spacing = np.where(ok, s, NO_LEADER_GAP_M)
    lead_v = np.where(ok, lead_speed, speed)  # delta_v 0 without a leader
    sumo_gap = np.where(ok, gap, NO_LEADER_GAP_M)
    lead_decel = np.where(ok, lead_shape[:, 2], STOP_DECEL_MPS2)
    # A red light, or the end of a lane the vehicle must leave: a standing leader there.
    closer = stop_m + length < spacing
    spacing = np.where(closer, stop_m + length, spacing)
    lead_v = np.where(closer, 0.0, lead_v)
    sumo_gap = np.where(closer, np.maximum(stop_m - min_gap, 0.0), sumo_gap)
    lead_decel = np.where(closer, STOP_DECEL_MPS2, lead_decel)
    driven = {v: i for i, v in enumerate(vids)}
    lead_index = np.fromiter(map(driven.get, lead_ids, repeat(-1)), np.int64, n)
    lead_index = np.where(ok & ~closer, lead_index, -1)
    limit = sec.limits_mps[edge, np.minimum(lane, sec.n_lanes[edge] - 1)]
    cols = [speed, limit, spacing, speed - lead_v]
    if observation == "lookahead":
        cols += list(section_lookahead(sec, lane, arc, edge, limit))
    return np.stack(cols, axis=1), sumo_gap, lead_decel, lead_index


def section_lookahead(
    sec: Section, lane: np.ndarray, arc_m: np.ndarray, edge: np.ndarray, own_limit: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The next edge's limit on the vehicle's lane index and the distance to that edge's
    start; on an open section's last edge the own limit and the distance to its end (the
    section env's definition, ``env.section_bank``)."""
    n_e = len(sec.edge_ids)
    if sec.closed:
        s = np.mod(arc_m, sec.length_m)
        nxt = (edge + 1) % n_e
        start = sec.offsets_m[nxt] + np.where(nxt == 0, sec.length_m, 0.0)
        return sec.limits_mps[nxt, np.minimum(lane, sec.n_lanes[nxt] - 1)], start - s
    last = edge == n_e - 1
    nxt = np.minimum(edge + 1, n_e - 1)
    limit = np.where(last, own_limit, sec.limits_mps[nxt, np.minimum(lane, sec.n_lanes[nxt] - 1)])
    start = np.where(last, sec.length_m, sec.offsets_m[nxt])
    return limit, start - arc_m


def states_of(states: dict[str, tuple[str, float, float, float]]) -> VehicleStates:
    """``VehicleStates`` from a {vehicle: (lane ID, lane position, speed, acceleration)}
    dictionary (``Simulation.read_lane_states``'s, as the demand env reads them)."""
    ids = tuple(states)
    n = len(ids)
    vals = list(states.values())
    return VehicleStates(
        ids,
        [s[0] for s in vals],
        np.fromiter((s[1] for s in vals), float, n),
        np.fromiter((s[2] for s in vals), float, n),
        np.fromiter((s[3] for s in vals), float, n),
    )

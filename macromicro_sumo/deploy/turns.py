"""Turners in a deployment (``deploy.turns``): driven vehicles whose route leaves the
section at a junction of it (a right turn off a signalised arterial), from the route SUMO
holds for them (``sumo.simulation.Simulation.route_ahead``).

The section's look-ahead (``road.section.Section.lookahead``) shows every vehicle the next
section edge's limit, so a turner approaches its turn at the through speed. On drawn arterial
528 (docs/deploy-log.md, stop 43, hA43) its approach 0-5 m before the line was 9.1 m/s
(truth 7.4, the turn's internal lane 6.51), and 17 of 58 emergency brakings of runs 0-1 were
turners handed back to SUMO inside the turn's internal lane, braked there at 5-9 m/s^2.

* ``limit``: the turner's look-ahead on its exit edge is the turn's limit at the stop line
  (``deploy.observe.observe_rows``' ``turns``);
* ``handover``: the turner is handed back to SUMO's model on its exit edge once the line is
  within ``handover_reach_m``, so that SUMO's own driver approaches the link and slows for
  the turn as the ground truth's do.

A vehicle's route is asked of SUMO when it is first seen on a section edge from which a
connection leaves the section (a "junction edge"), and again on each junction edge it
comes to (a loop's next lap included): a trip's route is the one SUMO found for it, a
rerouter's new route is SUMO's from the edge the rerouter sits on (it reroutes on entry,
before the read). A route SUMO changes while the vehicle is on the junction edge or its
junction's internal lane (a rerouting device's periodic reroute, a TraCI client's
changeTarget) is read again ``ROUTE_RECHECK_S`` after the last read at the latest. About one
call per vehicle and ``ROUTE_RECHECK_S``, not per step (the bench's budget,
``scripts/bench_deploy.py``); a section with no junction edge (no connection off it:
netgen_corridor, Bremen) asks nothing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from macromicro_sumo.deploy.observe import LaneTable
from macromicro_sumo.deploy.slots import VehicleSlots
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.inputs import read_net
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates

# Beyond the braking distance to the turn's limit and a step's travel: room for a few
# steps of SUMO's own driving before the line (its approach to the link registered).
HANDOVER_MARGIN_M = 10.0
NONE = np.zeros(0, dtype=np.int64)  # no vehicle (read only)
# A vehicle's route is asked again this long after its last read while it stays on its
# junction edge (and the internal lane after it, part of the edge's arc): a reroute meanwhile
# is seen within it, about 28 m at 14 m/s, well before the hand-over's reach of a turner.
ROUTE_RECHECK_S = 2.0


def handover_reach_m(
    speed_mps: np.ndarray, turn_limit_mps: np.ndarray, decel_mps2: np.ndarray, dt_s: float
) -> np.ndarray:
    """Distance before the stop line [m] from which a turner is SUMO's: its braking
    distance from ``speed_mps`` down to the turn's limit at its ``decel_mps2``, a step's
    travel and ``HANDOVER_MARGIN_M``."""
    excess = np.maximum(speed_mps**2 - turn_limit_mps**2, 0.0)
    return excess / (2.0 * decel_mps2) + speed_mps * dt_s + HANDOVER_MARGIN_M


def turn_limits(net_file: Path, section: Section) -> dict[tuple[int, str], float]:
    """(section edge index, edge off the section) -> the least limit of the internal lanes
    between them (the cautious one where several lanes turn; the outgoing lane's where the
    connection has no internal lane)."""
    net = read_net(net_file, with_internal=True)
    out: dict[tuple[int, str], float] = {}
    for i, eid in enumerate(section.edge_ids):
        for lane in net.getEdge(eid).getLanes():
            for con in lane.getOutgoing():
                to = con.getToLane()
                via = con.getViaLaneID()
                limit = net.getLane(via).getSpeed() if via else to.getSpeed()
                key = (i, to.getEdge().getID())
                out[key] = min(out.get(key, np.inf), float(limit))
    return out


def junction_edges(section: Section, limits: dict[tuple[int, str], float]) -> np.ndarray:
    """(E,) bool: the section's junction edges, those with a connection off the section
    (``turn_limits``' keys ``limits``; an open section's last edge has none: leaving there
    is leaving the section at its end)."""
    n = len(section.edge_ids)
    nxt = {i: section.edge_ids[(i + 1) % n] for i in range(n if section.closed else n - 1)}
    junction = np.zeros(n, dtype=bool)
    for i, to in limits:
        junction[i] |= i in nxt and to != nxt[i]
    return junction


class Turns:
    """Which driven vehicles turn off the section at the end of the junction edge they are
    on: per vehicle on a junction edge, (that edge's index, the arc of its stop line, the
    turn's limit [m/s]; NaN: it goes on), asked of SUMO when it comes onto the edge and
    dropped when it leaves it (kept for the vehicles of the last call only)."""

    def __init__(self, section: Section, net_file: Path, dt_s: float = 0.5) -> None:
        self.section, self.dt_s = section, dt_s
        self.limits = turn_limits(net_file, section)
        self.junction = junction_edges(section, self.limits)
        self.any = bool(self.junction.any())  # else no vehicle can turn: nothing to do
        self.lines_m = np.asarray(section.offsets_m + section.lengths_m, dtype=float)
        # vehicle -> (edge index, turn limit, the call (``calls``) it was read at)
        self.read: dict[str, tuple[int, float, int]] = {}
        self.calls = 0  # of ``ahead``: one a step
        self.recheck = max(1, round(ROUTE_RECHECK_S / dt_s))  # calls
        self._on: np.ndarray | None = None  # per lane code of a ``LaneTable``: on a junction edge

    def turn_at(self, edge: int, route: tuple[str, ...]) -> float:
        """The turn's limit where ``route`` (from section edge ``edge`` on) leaves the
        section at that edge's end; NaN where it goes on along the section or ends there."""
        sec = self.section
        if len(route) < 2 or route[0] != sec.edge_ids[edge]:
            return np.nan
        if route[1] == sec.edge_ids[(edge + 1) % len(sec.edge_ids)]:
            return np.nan
        return float(self.limits.get((edge, route[1]), np.nan))

    def ahead(
        self, vehicle_ids: list[str], lanes: LaneTable, codes: np.ndarray, pos_m: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of vehicles ``vehicle_ids`` on lanes ``codes`` of the section's ``LaneTable`` at
        lane positions ``pos_m``, those on their exit edge before its stop line: (their
        indices, the turn's limit, the line's arc)."""
        if not self.any:
            return NONE, NONE.astype(float), NONE.astype(float)
        edge = lanes.cols[0]
        if self._on is None or len(self._on) != len(edge):
            known = edge == edge  # NaN off the table (code 0)
            self._on = np.zeros(len(edge), dtype=bool)
            self._on[known] = self.junction[edge[known].astype(np.int64)]
        idx = self._on[codes].nonzero()[0]
        old, new = self.read, {}
        self.calls = now = self.calls + 1
        due = now - self.recheck
        at = edge[codes[idx]].astype(np.int64).tolist()
        route, turn_at = Simulation.route_ahead, self.turn_at
        for i, e in zip(idx.tolist(), at, strict=True):
            v = vehicle_ids[i]
            got = old.get(v)
            # Onto this junction edge, or read ROUTE_RECHECK_S ago (a reroute since): ask SUMO.
            if got is None or got[0] != e or got[2] <= due:
                got = (e, turn_at(e, route(v)), now)
            new[v] = got
        self.read = new  # the vehicles gone off junction edges dropped
        limit = np.fromiter((new[vehicle_ids[i]][1] for i in idx.tolist()), float, len(idx))
        line = self.lines_m[np.asarray(at, dtype=np.int64)]
        c = codes[idx]
        arc = lanes.arc0_m[c] + pos_m[idx] * lanes.arc_per_m[c]
        keep = ((limit == limit) & (arc <= line)).nonzero()[0]
        return idx[keep], limit[keep], line[keep]

    def to_hand(
        self, vehicle_ids: list[str], lanes: LaneTable, codes: np.ndarray, rows: np.ndarray,
        slots: np.ndarray, st: VehicleStates, vslots: VehicleSlots,
    ) -> np.ndarray:  # fmt: skip
        """deploy.turns "handover": the indices of the turners among driven vehicles
        ``vehicle_ids`` (rows ``rows`` of ``st``, slots ``slots`` of ``vslots``) that are
        within ``handover_reach_m`` of their line."""
        if not self.any:  # Bremen, netgen_corridor: the handover costs a call a step
            return NONE
        pos = st.pos_m[rows]
        idx, limit, line = self.ahead(vehicle_ids, lanes, codes, pos)
        if not idx.size:
            return idx
        at = codes[idx]
        arc = lanes.arc0_m[at] + pos[idx] * lanes.arc_per_m[at]
        dt = self.dt_s
        reach = handover_reach_m(st.speed_mps[rows[idx]], limit, vslots.decel[slots[idx]], dt)
        return idx[line - arc <= reach]

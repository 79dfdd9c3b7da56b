"""Turners in a deployment (``deploy.turns``): driven vehicles whose route leaves the
section at a junction of it (a right turn off a signalised arterial), read once per vehicle
when it enters the section.

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

Routes come from the run's route files (a flow's vehicles ``FLOW.N`` drive its route), the
turn's limit from the network: only ``sumo.simulation`` may ask SUMO, and it has no route
query. A vehicle whose route the files do not give (a trip, a rerouted vehicle) is taken
as staying on the section: it is driven as with ``off``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from macromicro_sumo.deploy.observe import LaneTable
from macromicro_sumo.deploy.slots import VehicleSlots
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.inputs import parse_xml, read_net
from macromicro_sumo.sumo.states import VehicleStates

# Beyond the braking distance to the turn's limit and a step's travel: room for a few
# steps of SUMO's own driving before the line (its approach to the link registered).
HANDOVER_MARGIN_M = 10.0
NO_EXIT = (-1, np.inf, np.nan)  # (exit edge, line arc, turn limit) of a through vehicle


def handover_reach_m(
    speed_mps: np.ndarray, turn_limit_mps: np.ndarray, decel_mps2: np.ndarray, dt_s: float
) -> np.ndarray:
    """Distance before the stop line [m] from which a turner is SUMO's: its braking
    distance from ``speed_mps`` down to the turn's limit at its ``decel_mps2``, a step's
    travel and ``HANDOVER_MARGIN_M``."""
    excess = np.maximum(speed_mps**2 - turn_limit_mps**2, 0.0)
    return excess / (2.0 * decel_mps2) + speed_mps * dt_s + HANDOVER_MARGIN_M


def file_routes(route_files: tuple[Path, ...]) -> dict[str, tuple[str, ...]]:
    """Vehicle or flow ID -> its route's edges, from SUMO route files (named ``<route>``s
    referenced by ``route=``, or a ``<route>`` inside the vehicle or flow)."""
    named: dict[str, tuple[str, ...]] = {}
    out: dict[str, tuple[str, ...]] = {}
    for f in route_files:
        root = parse_xml(f)  # gzip too, as SUMO reads them; a non-XML file is one line
        for r in root.iter("route"):
            if r.get("id") and r.get("edges"):
                named[r.get("id")] = tuple(r.get("edges").split())
        for tag in ("vehicle", "flow"):
            for v in root.iter(tag):
                inner = v.find("route")
                if inner is not None and inner.get("edges"):
                    out[v.get("id")] = tuple(inner.get("edges").split())
                elif v.get("route") in named:
                    out[v.get("id")] = named[v.get("route")]
    return out


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


class Turns:
    """Per driven vehicle that turns off the section: (exit edge index, arc of its stop
    line, the turn's limit [m/s]). Read from its route once, when it enters."""

    def __init__(
        self, section: Section, net_file: Path, route_files: tuple[Path, ...], dt_s: float
    ) -> None:
        self.section, self.dt_s = section, dt_s
        self.index = {e: i for i, e in enumerate(section.edge_ids)}
        self.routes = file_routes(route_files)
        self.limits = turn_limits(net_file, section)
        self.exit: dict[str, tuple[int, float, float]] = {}

    def enter(self, vehicle_ids: list[str]) -> None:
        """Read the routes of vehicles entering the section (a vehicle read once)."""
        for vid in vehicle_ids:
            if vid not in self.exit:
                route = self.routes.get(vid) or self.routes.get(vid.rpartition(".")[0])
                self.exit[vid] = self.exit_of(route) if route else NO_EXIT

    def exit_of(self, route: tuple[str, ...]) -> tuple[int, float, float]:
        """Where ``route`` leaves the section at one of its junctions: (edge index, arc of
        the stop line, the turn's limit); ``NO_EXIT`` where it stays on to the section's
        end (or leaves where an open section ends)."""
        sec, n = self.section, len(self.section.edge_ids)
        for k, edge in enumerate(route[:-1]):
            i = self.index.get(edge)
            if i is None or (not sec.closed and i == n - 1):
                continue
            if route[k + 1] == sec.edge_ids[(i + 1) % n]:
                continue
            limit = self.limits.get((i, route[k + 1]), np.nan)
            return i, float(sec.offsets_m[i] + sec.lengths_m[i]), float(limit)
        return NO_EXIT

    def ahead(
        self, vehicle_ids: list[str], lanes: LaneTable, codes: np.ndarray, pos_m: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of vehicles ``vehicle_ids`` on lanes ``codes`` of the section's ``LaneTable`` at
        lane positions ``pos_m``, those on their exit edge before its stop line: (their
        indices, the turn's limit, the line's arc)."""
        got = [self.exit.get(v, NO_EXIT) for v in vehicle_ids]
        ex = np.fromiter((g[0] for g in got), np.int64, len(got))
        line = np.fromiter((g[1] for g in got), float, len(got))
        limit = np.fromiter((g[2] for g in got), float, len(got))
        arc = lanes.arc0_m[codes] + pos_m * lanes.arc_per_m[codes]
        edge = lanes.cols[0][codes]  # NaN off the table: never an exit edge
        idx = ((ex == edge) & (arc <= line) & (limit == limit)).nonzero()[0]
        return idx, limit[idx], line[idx]

    def to_hand(
        self, vehicle_ids: list[str], lanes: LaneTable, codes: np.ndarray, rows: np.ndarray,
        slots: np.ndarray, st: VehicleStates, vslots: VehicleSlots,
    ) -> np.ndarray:  # fmt: skip
        """deploy.turns "handover": the indices of the turners among driven vehicles
        ``vehicle_ids`` (rows ``rows`` of ``st``, slots ``slots`` of ``vslots``) that are
        within ``handover_reach_m`` of their line."""
        pos = st.pos_m[rows]
        idx, limit, line = self.ahead(vehicle_ids, lanes, codes, pos)
        if not idx.size:
            return idx
        at = codes[idx]
        arc = lanes.arc0_m[at] + pos[idx] * lanes.arc_per_m[at]
        dt = self.dt_s
        reach = handover_reach_m(st.speed_mps[rows[idx]], limit, vslots.decel[slots[idx]], dt)
        return idx[line - arc <= reach]

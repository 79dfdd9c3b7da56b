"""The next red or yellow stop line of each vehicle (``Simulation.stop_lines`` and
``stop_lines_m``), from SUMO's answers and the net file's stopOffsets, with what a run asks
of SUMO once: a signal's link lanes and whether a vehicle's lane carries it on to a link.

``sumo.simulation`` hands in libsumo's functions (only it imports libsumo), so this is
plain Python over their answers.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np

from macromicro_sumo.sumo.states import STOP_STATES, SUMO_STOPLINE_GAP_M, StopLines
from macromicro_sumo.sumo.stop_offsets import StopOffset

# libsumo's answers this reads: getNextTLS, getLaneID, getBestLanes, getControlledLinks,
# getVehicleClass of a vehicle, and jmStoplineGap of a vehicle's vType (None: SUMO's 1 m).
BestLanes = Callable[[str], Sequence[tuple]]


class StopLineReader:
    """One run's stop-line queries. ``carry`` holds ``_carries_on``'s answers by vehicle,
    asked once per vehicle, lane and link lane; ``forget`` drops a vehicle's (SUMO's
    arrivals each step, removals): it holds only vehicles still in the network."""

    def __init__(
        self,
        next_tls: Callable[[str], Sequence[tuple[str, int, float, str]]],
        lane_of: Callable[[str], str],
        best_lanes: BestLanes,
        controlled_links: Callable[[str], Sequence[Sequence[tuple[str, str, str]]]],
        vehicle_class: Callable[[str], str],
        stopline_gap: Callable[[str], float | None],
        stop_offsets: dict[str, StopOffset],
    ) -> None:
        self._next_tls, self._lane_of, self._best_lanes = next_tls, lane_of, best_lanes
        self._controlled_links, self._vehicle_class = controlled_links, vehicle_class
        self._stopline_gap, self._stop_offsets = stopline_gap, stop_offsets
        self._links: dict[tuple[str, int], str] = {}  # ``_link_lane``'s, asked once a run
        self.carry: dict[str, dict[tuple[str, str], bool]] = {}  # vehicle -> _carries_on's

    def forget(self, vehicle_ids: Iterable[str]) -> None:
        """Vehicles gone from the network: their ``carry`` answers dropped."""
        pop = self.carry.pop
        for vid in vehicle_ids:
            pop(vid, None)

    def stop_lines(self, vehicle_ids: Sequence[str]) -> StopLines:
        """``Simulation.stop_lines``."""
        got = list(map(self.stop_line, vehicle_ids))
        dist, lanes, own, offset = (list(c) for c in zip(*got, strict=True)) if got else ([],) * 4
        return StopLines(np.array(dist), lanes, np.array(own), np.array(offset))

    def stop_line(self, vid: str) -> tuple[float, str, bool, float]:
        """``stop_lines``' (distance, lane, own, stopOffset) of one vehicle, plain values."""
        for tls, link, d, state in (ahead := self._next_tls(vid)):
            if state in STOP_STATES:
                lane = self._links.get((tls, link)) or self._link_lane(tls, link)
                here, own, offset = (self._lane_of(vid) if lane else lane), True, 0.0
                if here != lane:
                    known = self.carry.setdefault(vid, {})
                    if (own := known.get((here, lane))) is None:
                        own = known[here, lane] = self._carries_on(vid, here, lane)
                so = self._stop_offsets.get(lane) if self._stop_offsets else None
                if so is not None and so.applies(self._vehicle_class(vid)):
                    offset = so.value_m
                return d, lane, own, offset
        return (np.inf if ahead else np.nan), "", True, 0.0

    def _link_lane(self, tls: str, link: int) -> str:
        """A signal's link's incoming lane ("": none), asked of SUMO once a run."""
        got = enumerate(self._controlled_links(tls))
        self._links.update(((tls, k), ls[0][0] if ls else "") for k, ls in got)
        return self._links[tls, link]

    def stop_lines_m(self, vehicle_ids: Sequence[str]) -> np.ndarray:
        """``Simulation.stop_lines_m``, in plain floats: ``StopLines.line_m``'s arithmetic
        (a driver's few a step: StopLines' arrays cost ~30 us)."""
        out = []
        for vid in vehicle_ids:
            d, _, own, offset = self.stop_line(vid)
            gap = SUMO_STOPLINE_GAP_M
            if offset and (got := self._stopline_gap(vid)) is not None:
                gap = got
            out.append(d - max(offset - gap, 0.0) if own else np.inf + d)
        return np.array(out, dtype=float)

    def _carries_on(self, vehicle_id: str, lane: str, lane_id: str) -> bool:
        """Whether ``lane_id``, not the vehicle's ``lane``, is on its best lanes'
        continuation (SUMO's driver stops at its links; True in a junction, where its best
        lanes start after)."""
        if not lane.startswith(":") and lane.rpartition("_")[0] == lane_id.rpartition("_")[0]:
            return False  # another lane of the same edge
        for best, _length, _occ, _offset, _cont, chain in self._best_lanes(vehicle_id):
            if best == lane:
                return lane_id in chain
        return True

"""The next red or yellow stop line of each vehicle (``Simulation.stop_lines`` and
``stop_lines_m``), from SUMO's answers and the net file's stopOffsets, with what a run asks
of SUMO once: a signal's link lanes and whether a vehicle's lane carries it on to a link.

A yellow is a stop, but where the reader is told to decide it at onset
(``StopLineReader.decide_yellow``): then each vehicle decides each yellow once, the first
step it sees it, as SUMO's drivers do (``canBrakeBeforeStopLine``): a stop where it can
still brake before the line at its decel (``euler_brake_gap`` at most its distance less its
jmStoplineGap), else it passes while the light stays yellow; a red is always a stop. In the
ground truth of drawn arterials 528, 521 and 565 (4 runs, every yellow onset, cars within
120 m of the line) none of the 3,610 cars that could brake so crossed on the yellow, and
75-88% of the 329 that could not did.

``deploy.yellow = "sumo"`` decides as SUMO's ``MSVehicle::planMoveInternal`` does
(``sumo_stop_decel``, ``StopLineReader.decide_yellow``'s ``by_offset``): from the state at
the start of the step in which the light switches (``Upcoming`` within 0 s; ``"ahead"``'s
within one step decides a step before that, a step further from the line), a stop where
``seen - stopOffset >= brakeGap(v, max(min(3, emergencyDecel), decel))``: the lane's
stopOffset, not jmStoplineGap (that is only where it stops, and nearer the line where its
braking distance leaves less: ``StopLineReader._brake_room``).

``deploy.green = "switch"`` (``StopLineReader.decide_green``): a red link that turns green
at the start of the coming step (``Upcoming`` within 0 s) is no stop now, as SUMO's drivers
move off within the step the light switches in; read as it shows, the queue's head stood a
step longer at every green (drawn 1706, 4 runs: the head's first move 0.4 s after the
truth's, the truth's head 1.1 m/s at the first green sample, the policy's 0.2).

``sumo.simulation`` hands in libsumo's functions (only it imports libsumo), so this is
plain Python over their answers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from macromicro_sumo.sumo.states import STOP_STATES, SUMO_STOPLINE_GAP_M, StopLines
from macromicro_sumo.sumo.stop_offsets import StopOffset

# libsumo's answers this reads: getNextTLS, getLaneID, getBestLanes, getControlledLinks,
# getVehicleClass of a vehicle, and jmStoplineGap of a vehicle's vType (None: SUMO's 1 m).
BestLanes = Callable[[str], Sequence[tuple]]
# Signal states that are a yellow (``StopLineReader.decide_yellow``); red-yellow (u) is a red.
YELLOW_STATES = frozenset("yY")
GREEN_STATES = frozenset("gG")
# SUMO's --tls.yellow.min-decel (default 3 m/s^2): a driver deciding a yellow or red brakes at
# least this hard, at most at its emergencyDecel (MSVehicle::planMoveInternal's stopDecel).
TLS_YELLOW_MIN_DECEL_MPS2 = 3.0
POSITION_EPS_M = 0.1  # SUMO's POSITION_EPS: the nearest a stop before a line falls to it


def sumo_stop_decel(
    decel_of: Callable[[str], float], emergency_of: Callable[[str], float]
) -> Callable[[str], float]:
    """A vehicle's braking [m/s^2] in SUMO's yellow decision: its decel, raised to
    ``TLS_YELLOW_MIN_DECEL_MPS2`` where its emergencyDecel allows (libsumo's getDecel,
    getEmergencyDecel handed in)."""

    def stop_decel(vid: str) -> float:
        return max(min(TLS_YELLOW_MIN_DECEL_MPS2, emergency_of(vid)), decel_of(vid))

    return stop_decel


def euler_brake_gap(speed_mps: float, decel_mps2: float, dt_s: float) -> float:
    """SUMO's brakeGap [m] in Euler steps (``road.physics.brake_gap``'s, for one vehicle:
    the sumo layer does not import road)."""
    reduction = decel_mps2 * dt_s
    steps = math.floor(speed_mps / reduction)
    return dt_s * (steps * speed_mps - reduction * steps * (steps + 1.0) / 2.0)


class Upcoming:
    """A light's program's next phase's state string where its next switch
    (getNextSwitch) is at most ``within_s`` from now, else None: ``StopLineReader.
    decide_yellow``'s ``upcoming``. ``within_s`` 0 (``deploy.yellow = "sumo"``): SUMO
    switches a light at the start of the step that begins at its switch time, before its
    drivers move, so it says the yellow on exactly that step; one step (``"ahead"``): it
    says it a step before too, and the reader decides there (measured, SUMO 1.28: at
    t = 30.0 a light switching at 30.0 still shows green, at 30.5 yellow). ``sumo``: libsumo,
    handed in by ``Simulation`` (the only module that imports it); a program's phase states
    are read once."""

    def __init__(self, sumo, within_s: float) -> None:
        self._tl, self._time, self._dt = sumo.trafficlight, sumo.simulation.getTime, float(within_s)
        self._phases: dict[tuple[str, str], list[str]] = {}

    def __call__(self, tls: str) -> str | None:
        tl = self._tl
        if tl.getNextSwitch(tls) - self._time() > self._dt + 1e-6:
            return None
        key = (tls, tl.getProgram(tls))
        if (phases := self._phases.get(key)) is None:
            logics = tl.getAllProgramLogics(tls)
            logic = next((lg for lg in logics if lg.programID == key[1]), logics[0])
            phases = self._phases[key] = [p.state for p in logic.phases]
        return phases[(tl.getPhase(tls) + 1) % len(phases)]


def yellow_rule(sumo, dt_s: float, ahead: bool, by_sumo: bool) -> tuple:
    """``StopLineReader.decide_yellow``'s arguments from libsumo (``sumo``, handed in by
    ``Simulation``) for steps of ``dt_s``: onset's (getSpeed, getDecel; neither flag),
    ``ahead``'s (an ``Upcoming`` within a step) or SUMO's own (``by_sumo``: ``Upcoming``
    within 0 s, ``sumo_stop_decel``, the line less its stopOffset)."""
    veh, dt = sumo.vehicle, float(dt_s)
    if by_sumo:
        decel = sumo_stop_decel(veh.getDecel, veh.getEmergencyDecel)
        return veh.getSpeed, decel, dt, Upcoming(sumo, 0.0), True
    return veh.getSpeed, veh.getDecel, dt, (Upcoming(sumo, dt) if ahead else None), False


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
        # ``decide_yellow``: a vehicle's speed and decel, the step; None: a yellow is a stop.
        self._yellow_by: tuple[Callable[[str], float], Callable[[str], float], float] | None
        self._yellow_by = None
        self._by_offset = False  # ``decide_yellow``'s: the line less its stopOffset (SUMO's)
        self._upcoming: Callable[[str], str | None] | None = None
        self._greens: Callable[[str], str | None] | None = None  # ``decide_green``'s
        self.passing: dict[str, set[tuple[str, int]]] = {}  # vehicle -> yellow links it passes
        self._decided: dict[str, set[tuple[str, int]]] = {}  # vehicle -> yellow links decided
        # ``by_offset``: vehicle -> {red or yellow link: ``_brake_room``, from its first sight}
        self._rooms: dict[str, dict[tuple[str, int], float]] = {}

    def decide_yellow(
        self,
        speed_of: Callable[[str], float],
        decel_of: Callable[[str], float],
        dt_s: float,
        upcoming: Callable[[str], str | None] | None = None,
        by_offset: bool = False,
    ) -> None:
        """From now on each vehicle decides each yellow at its onset (the module's rule),
        from its speed and decel (libsumo's getSpeed, getDecel) in steps of ``dt_s``.
        ``upcoming``: a light's state string from the coming step on where it switches
        then (None: it does not): a green link turning yellow is decided now, as SUMO's
        drivers meet the switch within that step (the light switches before they move),
        where a driver that waits for it decides a step late, a step nearer the line; one
        that says it a step before the switch too (``Upcoming`` within a step,
        ``deploy.yellow = "ahead"``) decides there, a step before SUMO's drivers.
        ``by_offset``: it can stop where its braking distance is at most its distance less
        the link lane's stopOffset for its class (0: none), SUMO's canBrakeBeforeStopLine,
        not less its jmStoplineGap."""
        self._yellow_by = (speed_of, decel_of, float(dt_s))
        self._upcoming = upcoming
        self._by_offset = bool(by_offset)

    def decide_green(self, upcoming: Callable[[str], str | None]) -> None:
        """From now on a red link whose light switches to green at the start of the coming
        step (``upcoming``: the light's state string from the coming step on where it switches
        then, ``Upcoming`` within 0 s) is no stop: SUMO switches the light before its drivers
        move, so they start within that step; a driver that waits to see the green starts a
        step later (``deploy.green = "switch"``)."""
        self._greens = upcoming

    def forget(self, vehicle_ids: Iterable[str]) -> None:
        """Vehicles gone from the network: their ``carry`` answers and yellow decisions
        dropped."""
        for held in (self.carry, self.passing, self._decided, self._rooms):
            if held:
                for vid in vehicle_ids:
                    held.pop(vid, None)

    def _passes(self, vid: str, key: tuple[str, int], d: float) -> bool:
        """Whether ``vid`` passes the yellow link ``key`` ``d`` m ahead: decided the first
        step it sees this yellow (``decide_yellow``), kept while the link stays yellow."""
        decided = self._decided.setdefault(vid, set())
        if key not in decided:
            speed_of, decel_of, dt = self._yellow_by
            if self._by_offset:
                stop_m = d - self._link_offset(vid, key)
            else:
                gap = self._stopline_gap(vid)
                stop_m = d - (SUMO_STOPLINE_GAP_M if gap is None else gap)
            decided.add(key)
            if stop_m < euler_brake_gap(speed_of(vid), decel_of(vid), dt):
                self.passing.setdefault(vid, set()).add(key)
        return key in self.passing.get(vid, ())

    def _brake_room(self, vid: str, d: float, offset: float) -> float:
        """How far [m] a red or yellow line ``d`` m ahead of ``vid`` moves on so that the
        driver's stop before it (``stop_lines_m``, less max(jmStoplineGap, stopOffset)) lands
        where SUMO's driver stops (``decide_yellow``'s ``by_offset``; planMoveInternal's
        laneStopOffset): at most that far before the line, no further than its braking
        distance at its stop decel allows (at least POSITION_EPS before it), so a stop decided
        within that distance brakes at its decel; 0 where it cannot stop before the line.
        Asked once, at the first step the line stops it (SUMO's driver, braking at that
        decel, keeps the same room; a driver braking softer first would move it on to the
        line, the front over a loop 0.5 m before it: 1161's stop-line loops' error doubled)."""
        speed_of, decel_of, dt = self._yellow_by
        gap = self._stopline_gap(vid)
        major = max(SUMO_STOPLINE_GAP_M if gap is None else gap, offset)
        room = d - euler_brake_gap(speed_of(vid), decel_of(vid), dt)
        return major - max(room, POSITION_EPS_M) if 0.0 <= room < major else 0.0

    def _link_offset(self, vid: str, key: tuple[str, int]) -> float:
        """The stopOffset [m] of link ``key``'s lane for ``vid``'s class (0: none)."""
        lane = self._links.get(key) or self._link_lane(*key)
        so = self._stop_offsets.get(lane) if self._stop_offsets else None
        return so.value_m if so is not None and so.applies(self._vehicle_class(vid)) else 0.0

    def _undecide(self, vid: str, key: tuple[str, int]) -> None:
        """The link ``key`` is no longer yellow: ``vid``'s decision of it dropped (the next
        yellow is decided afresh)."""
        if key in self._decided.get(vid, ()):
            self._decided[vid].discard(key)
            self.passing.get(vid, set()).discard(key)

    def stop_lines(self, vehicle_ids: Sequence[str]) -> StopLines:
        """``Simulation.stop_lines``."""
        got = list(map(self.stop_line, vehicle_ids))
        dist, lanes, own, offset = (list(c) for c in zip(*got, strict=True)) if got else ([],) * 4
        return StopLines(np.array(dist), lanes, np.array(own), np.array(offset))

    def stop_line(self, vid: str) -> tuple[float, str, bool, float]:
        """``stop_lines``' (distance, lane, own, stopOffset) of one vehicle, plain values."""
        for tls, link, d, state in (ahead := self._next_tls(vid)):
            if self._upcoming is not None and state in GREEN_STATES:
                nxt = self._upcoming(tls)
                if nxt is not None and link < len(nxt) and nxt[link] in YELLOW_STATES:
                    state = nxt[link]  # yellow from the coming step: decided now
            elif self._greens is not None and state in STOP_STATES:
                nxt = self._greens(tls)
                if nxt is not None and link < len(nxt) and nxt[link] in GREEN_STATES:
                    state = nxt[link]  # green from the coming step: SUMO's drivers go in it
            if self._yellow_by is not None:  # a yellow decided at onset (``decide_yellow``)
                if state in YELLOW_STATES:
                    if self._passes(vid, (tls, link), d):
                        continue  # it drives on while the light is yellow
                elif vid in self._decided:
                    self._undecide(vid, (tls, link))
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
                if self._by_offset and own:  # where it stops, planned once per light
                    held = self._rooms.setdefault(vid, {})
                    if (room := held.get((tls, link))) is None:
                        room = held[tls, link] = self._brake_room(vid, d, offset)
                    d += room
                return d, lane, own, offset
            if self._by_offset and (tls, link) in self._rooms.get(vid, ()):
                del self._rooms[vid][tls, link]  # green again: the next stop planned afresh
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

"""The SUMO boundary: the only module that talks to libsumo.

It builds SUMO's command line explicitly, starts one simulation per process (libsumo
allows no more) and reloads it for later runs, and exchanges plain numpy arrays (and
``sumo.states``' values) with the rest of the package. The ground truth and the environments compute leaders and gaps
from arc positions; a deployment on a user's network reads SUMO's own leader (``getLeader``
follows the network's lane connections, where lane indices shift at an added lane).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

import libsumo
import numpy as np
import sumolib

from macromicro_sumo.errors import UserError
from macromicro_sumo.sumo import direct, reads
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.states import DEFAULT_SPEED_MODE, StopLines, VehicleStates
from macromicro_sumo.sumo.stop_lines import StopLineReader, Upcoming, yellow_rule
from macromicro_sumo.sumo.stop_offsets import lane_stop_offsets

_C = libsumo.constants
_LANE_VARS = (_C.VAR_LANE_ID, _C.VAR_LANEPOSITION, _C.VAR_SPEED, _C.VAR_ACCELERATION)
# A driven vehicle's subscription: the lane state plus its leader within a look-ahead.
_DRIVE_VARS = (*_LANE_VARS, _C.VAR_LEADER)


def _compiled(names: str) -> list:
    """libsumo's compiled per-vehicle functions for a deployment's every step (wrappers as
    fallback): a wrapper adds a Python frame a call (getSpeed 0.23 -> 0.17 us, libsumo 1.28);
    the compiled getLeader answers ("", -1.0) where its wrapper may say None."""
    lib, v = getattr(libsumo, "_libsumo", None), libsumo.vehicle
    return [getattr(lib, f"vehicle_{f}", None) or getattr(v, f) for f in names.split()]


_GET_IDS, _GET_LANE, _GET_POS, _GET_SPEED, _GET_ACCEL, _GET_LEADER = _compiled(
    "getIDList getLaneID getLanePosition getSpeed getAcceleration getLeader"
)
# libsumo's wrapper of getLeader answers None for no leader (traci's legacy mode); the
# compiled function, ("", -1.0).
_LEADER_MAY_BE_NONE = _GET_LEADER is getattr(libsumo.vehicle, "getLeader", None)
_SET_SPEED, _OWN_SPEED, _BEST_LANES, _NEXT_TLS, _NEIGHBORS = _compiled(
    "setSpeed getSpeedWithoutTraCI getBestLanes getNextTLS getNeighbors"
)
# getNeighbors' mode of the left followers that block a change (traci's getLeftFollowers).
_LEFT_BLOCKERS = 4


def api_version() -> str:
    """libsumo's API version where a simulation runs ("" where none)."""
    return str(libsumo.getVersion()[1]) if _is_running() else ""


def _is_running() -> bool:
    with contextlib.suppress(Exception):
        return libsumo.simulation.getTime() is not None
    return False


class Driver(Protocol):
    """Who drives some of the vehicles of a run (a deployment): ``before_step`` is called
    once per step, before ``Simulation.step``; it reads the state it needs and sets speeds
    or vTypes. The ground truth's run loops take one (None: SUMO drives everyone)."""

    def before_step(self, sim: Simulation) -> None: ...


class Simulation:
    """One libsumo simulation, started once per process and reloaded for each run."""

    _started_pid: int | None = None  # class-level: libsumo holds one simulation per process
    _active: Simulation | None = None  # the instance whose run libsumo holds now

    def __init__(self, options: SumoOptions) -> None:
        self.options = options
        self._dt = float(options.step_length_s)
        self._load(options)

    # ------------------------------------------------------------------ lifecycle
    def _load(self, options: SumoOptions) -> None:
        args = options.args()
        try:
            if Simulation._started_pid == os.getpid() and _is_running():
                libsumo.load(args)
            else:
                libsumo.start([sumolib.checkBinary("sumo"), *args])
                Simulation._started_pid = os.getpid()
        except libsumo.TraCIException as exc:
            raise UserError(f"SUMO could not start with {options.net_file}: {exc}") from None
        except Exception as exc:  # libsumo says only "Process Error"; SUMO's message went to stderr
            raise UserError(
                f"SUMO could not start with {options.net_file} ({exc}); see SUMO's message above"
            ) from None
        self.options = options
        self._dt = float(options.step_length_s)
        self._states: VehicleStates | None = None
        self._lines = StopLineReader(
            _NEXT_TLS,
            _GET_LANE,
            _BEST_LANES,
            libsumo.trafficlight.getControlledLinks,
            libsumo.vehicle.getVehicleClass,
            lambda vid: self.vtype_stopline_gap(self.vehicle_type(vid)),
            lane_stop_offsets(Path(options.net_file)),
        )
        Simulation._active = self

    def is_active(self) -> bool:
        """False once another instance (or a close) took libsumo's one simulation."""
        return Simulation._active is self

    def reload(self) -> None:
        """Start this instance's run again after another instance (or a close) took libsumo's
        one simulation: a fresh run, nothing added through libsumo since its files loaded."""
        self._load(self.options)

    def close(self) -> None:
        """End this instance's run; a no-op when another instance has taken libsumo over."""
        if Simulation._started_pid == os.getpid() and Simulation._active in (self, None):
            with contextlib.suppress(Exception):
                libsumo.close()
            Simulation._started_pid = Simulation._active = None

    @property
    def dt_s(self) -> float:
        return self._dt

    def time_s(self) -> float:
        return float(libsumo.simulation.getTime())

    # ------------------------------------------------------------------ network
    def set_lane_speed_limits(self, lane_ids: Sequence[str], limits_mps: Sequence[float]) -> None:
        for lane, v in zip(lane_ids, limits_mps, strict=True):
            libsumo.lane.setMaxSpeed(lane, float(v))

    def lane_speed_limits(self, lane_ids: Sequence[str]) -> np.ndarray:
        return np.array([libsumo.lane.getMaxSpeed(lane) for lane in lane_ids])

    # ------------------------------------------------------------------ vehicles
    def add_vehicles(
        self, vehicle_ids: Sequence[str], route_ids: Sequence[str], type_ids: Sequence[str],
        lane_pos_m: Sequence[float], speeds_mps: Sequence[float],
    ) -> None:  # fmt: skip
        """Queue vehicles for insertion on lane 0 at exact positions and speeds (next step)."""
        for vid, route, vtype, pos, v in zip(
            vehicle_ids, route_ids, type_ids, lane_pos_m, speeds_mps, strict=True
        ):
            self.add_vehicle(vid, route, vtype, 0, pos, v)

    def pending_vehicles(self) -> tuple[str, ...]:
        return tuple(libsumo.simulation.getPendingVehicles())

    def vehicle_ids(self) -> tuple[str, ...]:
        return tuple(libsumo.vehicle.getIDList())

    def remove_vehicles(self, vehicle_ids: Sequence[str]) -> None:
        """Remove vehicles, subscribed or not: libsumo 1.28 fails every later step ("Vehicle
        ... is not known") when a subscribed vehicle is removed without unsubscribing it."""
        self._states = None
        self._lines.forget(vehicle_ids)
        for vid in vehicle_ids:
            with contextlib.suppress(libsumo.TraCIException):
                libsumo.vehicle.unsubscribe(vid)
            libsumo.vehicle.remove(vid)

    def set_speed_mode(self, vehicle_ids: Sequence[str], mode: int) -> None:
        list(map(libsumo.vehicle.setSpeedMode, vehicle_ids, [int(mode)] * len(vehicle_ids)))

    def set_speeds(self, vehicle_ids: Sequence[str], speeds_mps: Sequence[float]) -> None:
        """Speed commands for the next step (speed mode 0 applies them exactly)."""
        direct.send(_SET_SPEED, vehicle_ids, np.asarray(speeds_mps, dtype=float))

    def move_to(
        self, vehicle_ids: Sequence[str], lane_ids: Sequence[str], lane_pos_m: Sequence[float],
        route_ids: Sequence[str],
    ) -> None:  # fmt: skip
        """Place vehicles without insertion checks (soft reset); their routes restart there."""
        self._states = None
        for vid, lane, pos, route in zip(vehicle_ids, lane_ids, lane_pos_m, route_ids, strict=True):
            # moveTo first, then the lap route that starts on the new edge: the other order
            # can leave the vehicle on its route's last edge, and it vanishes at its end.
            libsumo.vehicle.moveTo(vid, lane, float(pos))
            libsumo.vehicle.setRouteID(vid, route)

    def place_vehicles(
        self, vehicle_ids: Sequence[str], type_ids: Sequence[str], lane_ids: Sequence[str],
        pos_m: Sequence[float], route_ids: Sequence[str], speeds_mps: Sequence[float],
        detours: Sequence[str],
    ) -> None:  # fmt: skip
        """Vehicles on the road made what ``add_vehicle`` + a step would insert: vType, lane,
        position, route, speed, acceleration 0 (the same trajectories after, tested). One
        placed on the lane it is on goes by its detour lane first: a moveTo along its own
        lane keeps the lane's vehicle order (SUMO 1.28), and it would keep its leaders."""
        self._states = None
        v = libsumo.vehicle
        for vid, vtype, lane, pos, route, speed, detour in zip(
            vehicle_ids, type_ids, lane_ids, pos_m, route_ids, speeds_mps, detours, strict=True
        ):
            if v.getTypeID(vid) != vtype:
                v.setType(vid, vtype)
            if v.getLaneID(vid) == lane:
                v.moveTo(vid, detour, 0.0)
            v.moveTo(vid, lane, float(pos))
            v.setRouteID(vid, route)  # after moveTo, as ``move_to`` has it
            v.setPreviousSpeed(vid, float(speed), 0.0)

    # ------------------------------------------------------------------ sections
    def add_route(self, route_id: str, edges: Sequence[str]) -> None:
        libsumo.route.add(route_id, list(edges))

    def add_vehicle(
        self, vehicle_id: str, route_id: str, type_id: str, lane: int, pos_m: float,
        speed_mps: float,
    ) -> None:  # fmt: skip
        """Queue one vehicle at an exact lane, position and speed (inserted next step)."""
        try:
            libsumo.vehicle.add(
                vehicle_id,
                route_id,
                typeID=type_id,
                depart="now",
                departLane=str(int(lane)),
                departPos=repr(float(pos_m)),
                departSpeed=repr(float(speed_mps)),
            )
        except libsumo.TraCIException as exc:
            raise UserError(
                f"SUMO refused vehicle {vehicle_id} at {pos_m:.2f} m, {speed_mps:.2f} m/s: {exc}"
            ) from None

    def read_lane_states(self) -> dict[str, tuple[str, float, float, float]]:
        """{vehicle: (lane ID, lane position, speed, acceleration)} of subscribed vehicles."""
        lane, pos, spd, acc = _LANE_VARS
        return {
            vid: (r[lane], r[pos], r[spd], r[acc])
            for vid, r in libsumo.vehicle.getAllSubscriptionResults().items()
            if lane in r
        }

    def subscribe_driving(self, vehicle_ids: Sequence[str], lookahead_m: float) -> None:
        """Subscribe vehicles to their lane state (``read_lane_states``) and their leader within
        ``lookahead_m``: one subscription each, since a second one would replace the first."""
        params = {_C.VAR_LEADER: float(lookahead_m)}
        for vid in vehicle_ids:
            libsumo.vehicle.subscribe(vid, _DRIVE_VARS, 0, 2**31 - 1, params)

    def read_leaders(self) -> dict[str, tuple[str, float]]:
        """{vehicle: (leader ID or "", SUMO's gap: leader's back - own front - minGap)} of the
        vehicles subscribed with ``subscribe_driving``."""
        res = libsumo.vehicle.getAllSubscriptionResults().items()
        return {vid: r[_C.VAR_LEADER] for vid, r in res if _C.VAR_LEADER in r}

    def has_traffic_lights(self) -> bool:
        return int(libsumo.trafficlight.getIDCount()) > 0

    def stop_line_m(self, vehicle_id: str) -> float:
        """``stop_lines_m`` of one vehicle, inf where none."""
        return float(np.fmin(self.stop_lines_m([vehicle_id])[0], np.inf))  # NaN: inf

    def signal_links(self) -> list[tuple[str, int, str, str, str]]:
        """(signal, link index, incoming, outgoing, internal lane) of every signalised link."""
        tl = libsumo.trafficlight
        by_tls = [(t, enumerate(tl.getControlledLinks(t))) for t in tl.getIDList()]
        return [(t, i, *link) for t, links in by_tls for i, ls in links for link in ls]

    def signal_states(self, signal_ids: Sequence[str]) -> list[tuple[str, int, float, str]]:
        """(program, phase index, seconds left in the phase, state string) of each signal."""
        tl, now = libsumo.trafficlight, libsumo.simulation.getTime()
        get = (tl.getProgram, tl.getPhase, tl.getNextSwitch, tl.getRedYellowGreenState)
        rows = [[f(t) for f in get] for t in signal_ids]
        return [(p, k, n - now, s) for p, k, n, s in rows]

    def set_signal_states(self, rows: Sequence[tuple[str, str, int, float]]) -> None:
        """Put each signal (ID, program, phase index, seconds left in the phase) where a
        recording saw it, its program running on; one this run lacks is left as it is."""
        tl = libsumo.trafficlight
        for t, program, phase, left_s in rows:
            with contextlib.suppress(libsumo.TraCIException):
                tl.setProgram(t, program)
                tl.setPhase(t, int(phase))
                tl.setPhaseDuration(t, float(left_s))

    def own_speeds(self, vehicle_ids: Sequence[str]) -> np.ndarray:
        """SUMO's own choice of the last step's speed where a command overrode it."""
        return direct.floats("o", (_OWN_SPEED,), vehicle_ids)[0]

    @staticmethod
    def blocked_changes(ids: Sequence[str], sides: Sequence[int]) -> tuple[np.ndarray, dict]:
        """Per (vehicle, side -1 right / 1 left) LC2013 urgently wants to change to for its route,
        blocked: its own last speed (NaN: none), and {a follower blocking it: its own speed}."""
        s, c = list(map(libsumo.vehicle.getLaneChangeState, ids, sides)), libsumo.constants
        hit = [x[0] & c.LCA_BLOCKED and not ~x[0] & (c.LCA_STRATEGIC | c.LCA_URGENT) for x in s]
        on = [(v, 4 + (d < 0), h) for v, d, h in zip(ids, sides, hit, strict=True)]
        back = {f: _OWN_SPEED(f) for v, m, h in on if h for f, _ in _NEIGHBORS(v, m)}
        return np.array([_OWN_SPEED(v) if h else np.nan for v, _, h in on]), back

    def left_blockers(self, vehicle_ids: Sequence[str]) -> set[str]:
        """The followers on the lane left of each vehicle that block its lane change."""
        return {f for v in vehicle_ids for f, _ in _NEIGHBORS(v, _LEFT_BLOCKERS)}

    def lane_end_m(self, vehicle_id: str, lane_id: str, pos_m: float) -> float:
        """``lane_end``'s distance alone (inf where the lane carries the vehicle on)."""
        return self.lane_end(vehicle_id, lane_id, pos_m)[0]

    def lane_end(self, vehicle_id: str, lane_id: str, pos_m: float) -> tuple[float, int]:
        """(front to where it must have left its lane(s) for its route, junctions counted, inf
        where it carries on; SUMO's best-lane offset there: changes needed, > 0 left). On a
        junction's internal lane, not asked: SUMO's best lanes there are the next edge's
        (its routes hold no internal edge), none of them the lane itself (inf, 0)."""
        if lane_id.startswith(":"):
            return float("inf"), 0
        for lane, length, _occ, offset, _cont, chain in _BEST_LANES(vehicle_id):
            if lane == lane_id and offset != 0:
                ends = zip(map(libsumo.lane.getLinks, chain[:-1]), chain[1:], strict=False)
                via = sum(next(k[7] for k in ks if k[0] == b) for ks, b in ends)
                return float(length - pos_m + via), int(offset)
        return float("inf"), 0

    def vtype_shape(self, type_id: str) -> tuple[float, float, float]:
        """(length, minGap, decel) of a vType [m, m, m/s^2]."""
        vt, t = libsumo.vehicletype, type_id
        return float(vt.getLength(t)), float(vt.getMinGap(t)), float(vt.getDecel(t))

    def vtype_stopline_gap(self, type_id: str) -> float | None:
        """A vType's jmStoplineGap [m], where its drivers stop before a red line; None where
        the vType sets none (SUMO's default, 1 m, for every carFollowModel)."""
        got = libsumo.vehicletype.getParameter(type_id, "junctionModel.jmStoplineGap")
        return float(got) if got else None

    def vtype_max_speed(self, type_id: str) -> float:
        return float(libsumo.vehicletype.getMaxSpeed(type_id))  # [m/s]; commands may exceed it

    def vtype_accel(self, type_id: str) -> float:
        return float(libsumo.vehicletype.getAccel(type_id))  # [m/s^2]; commands may exceed it

    def vtype_speed_factor(self, type_id: str) -> tuple[float, float]:
        """(mean, deviation) of the speedFactor SUMO draws each vehicle of a vType from."""
        vt = libsumo.vehicletype
        return float(vt.getSpeedFactor(type_id)), float(vt.getSpeedDeviation(type_id))

    def set_driver(self, vehicle_id: str, **params: float) -> None:
        """One vehicle's model parameters by libsumo's names (accel, minGap: ``set<Name>``)."""
        for name, value in params.items():
            getattr(libsumo.vehicle, f"set{name[0].upper()}{name[1:]}")(vehicle_id, float(value))

    def set_types(self, vehicle_ids: Sequence[str], type_ids: Sequence[str]) -> None:
        list(map(libsumo.vehicle.setType, vehicle_ids, type_ids))

    def speed_factors(self, vehicle_ids: Sequence[str]) -> np.ndarray:
        return np.array([libsumo.vehicle.getSpeedFactor(v) for v in vehicle_ids], dtype=float)

    def set_speed_factors(self, vehicle_ids: Sequence[str], factors: Sequence[float]) -> None:
        list(map(libsumo.vehicle.setSpeedFactor, vehicle_ids, map(float, factors)))

    def release_speeds(self, vehicle_ids: Sequence[str]) -> None:
        """Hand vehicles back to their own model: no speed command, SUMO's default mode."""
        for vid in vehicle_ids:
            libsumo.vehicle.setSpeed(vid, -1.0)
            libsumo.vehicle.setSpeedMode(vid, DEFAULT_SPEED_MODE)

    def departed(self) -> tuple[str, ...]:
        """Vehicles that entered the network in the last step."""
        return tuple(libsumo.simulation.getDepartedIDList())

    @staticmethod
    def route_ahead(vehicle_id: str) -> tuple[str, ...]:
        """The edges of a vehicle's route from the one it is on (or last left, on a junction)
        to its end, as SUMO holds it now: a trip's route SUMO found, a rerouter's new one."""
        v = libsumo.vehicle
        return tuple(v.getRoute(vehicle_id)[v.getRouteIndex(vehicle_id) :])

    @staticmethod
    def vehicle_type(vehicle_id: str) -> str:
        """The running SUMO's vType of a vehicle (libsumo drives one SUMO a process)."""
        return str(libsumo.vehicle.getTypeID(vehicle_id))

    def vehicle_class(self, type_id: str) -> str:
        """SUMO's vehicle class of a vType (lanes may admit only some classes)."""
        return str(libsumo.vehicletype.getVehicleClass(type_id))

    def set_lane_change_mode(self, vehicle_ids: Sequence[str], mode: int) -> None:
        list(map(libsumo.vehicle.setLaneChangeMode, vehicle_ids, [int(mode)] * len(vehicle_ids)))

    def move_to_lanes(
        self, vehicle_ids: Sequence[str], lane_ids: Sequence[str], lane_pos_m: Sequence[float]
    ) -> None:
        """Place vehicles on exact lanes and positions (replay of recorded traces)."""
        self._states = None
        for vid, lane, pos in zip(vehicle_ids, lane_ids, lane_pos_m, strict=True):
            libsumo.vehicle.moveTo(vid, lane, float(pos))

    def clear_vehicles(self) -> None:
        """Remove every vehicle, running or waiting to be inserted."""
        self.remove_vehicles(libsumo.vehicle.getIDList())
        for vid in libsumo.simulation.getPendingVehicles():
            with contextlib.suppress(libsumo.TraCIException):
                libsumo.vehicle.remove(vid)

    # ------------------------------------------------------------------ stepping
    def step(self) -> None:
        self._states = None
        libsumo.simulationStep()
        if self._lines.carry:  # only vehicles still in the network kept (a signal's nets)
            self._lines.forget(libsumo.simulation.getArrivedIDList())

    def collisions(self) -> int:
        """Vehicles in collision during the last step."""
        return int(libsumo.simulation.getCollidingVehiclesNumber())

    def colliding_vehicles(self) -> tuple[str, ...]:
        """The vehicles in collision during the last step (``collisions`` counts them)."""
        return tuple(libsumo.simulation.getCollidingVehiclesIDList())

    def teleports(self) -> int:
        return int(libsumo.simulation.getStartingTeleportNumber())

    # ------------------------------------------------------------------ bulk reads
    # A deployment's hot path: per-vehicle getters, ~0.9 us a vehicle for the four; a
    # subscription costs SUMO's step ~2.5 us a vehicle and ~2 us more to read (measured).
    def vehicle_states(self) -> VehicleStates:
        """Every vehicle on the road now, read once per step: whoever asks again before
        the next step (a recorder after it, a driver before the next) shares the read."""
        if self._states is None:
            ids = direct.vehicle_ids(_GET_IDS)
            pos, speed, accel = direct.floats("psa", (_GET_POS, _GET_SPEED, _GET_ACCEL), ids)
            self._states = VehicleStates(ids, direct.lanes(_GET_LANE, ids), pos, speed, accel)
        return self._states

    def lane_states(self, vehicle_ids: Sequence[str]) -> tuple[list[str], np.ndarray, np.ndarray]:
        """(lane ID, lane position [m], speed [m/s]) of the given vehicles, by compiled getters
        (the env cores' read: no ID list, no subscription); a vehicle not yet on the
        road has lane ID ""; one SUMO does not know raises ``KeyError``."""
        try:
            lanes = direct.lanes(_GET_LANE, vehicle_ids)
            pos, speed = direct.floats("ps", (_GET_POS, _GET_SPEED), vehicle_ids)
            return lanes, pos, speed
        except libsumo.TraCIException as exc:
            raise KeyError(str(exc)) from None

    def leaders(self, vehicle_ids: Sequence[str], lookahead_m: float) -> list[tuple[str, float]]:
        """(leader ID, SUMO's gap: leader's back - own front - minGap; ("", -1): none) of
        each vehicle within ``lookahead_m`` along the network's lanes (``getLeader``)."""
        # Only the wrapper (no compiled getLeader) may say None: the scan for it, ~2 us a
        # step of ~42 driven vehicles, is made only then; libsumo's C++ getLeader answers
        # as the compiled one.
        if not _LEADER_MAY_BE_NONE:
            return direct.leaders(_GET_LEADER, vehicle_ids, float(lookahead_m))
        out = reads.each(_GET_LEADER, vehicle_ids, float(lookahead_m))
        return [r or ("", -1.0) for r in out] if None in out else out

    def arrived(self) -> frozenset[str]:
        """Vehicles that left the network in the last step."""
        return frozenset(libsumo.simulation.getArrivedIDList())

    def decide_yellow(self, ahead: bool = False, sumo: bool = False) -> None:
        """Each vehicle asking its stop lines decides each yellow at its onset from now on
        (``sumo.stop_lines.yellow_rule``; ``ahead``: on the last green step but one; ``sumo``:
        on the switch's step, by SUMO's own rule): deploy.yellow."""
        self._lines.decide_yellow(*yellow_rule(libsumo, self._dt, ahead, sumo))

    def decide_green(self) -> None:
        """A red link whose light turns green at the start of the coming step is no stop
        from now on (``sumo.stop_lines.StopLineReader.decide_green``): deploy.green."""
        self._lines.decide_green(Upcoming(libsumo, 0.0))

    def stop_lines(self, vehicle_ids: Sequence[str]) -> StopLines:
        """The next red or yellow line of each vehicle (``StopLines``; every caller's query):
        getNextTLS, its link's lane (its own, or one its lane carries it on to?), that
        lane's stopOffset (``sumo.stop_lines``)."""
        return self._lines.stop_lines(vehicle_ids)

    def stop_lines_m(self, vehicle_ids: Sequence[str]) -> np.ndarray:
        """``StopLines.line_m`` with each vehicle's jmStoplineGap: its red line less what a
        lane's stopOffset adds; inf: no red or yellow ahead, or another lane's link (it stops
        0 m before its lane's end, ``lane_end``, not 1); NaN: no signal at all ahead."""
        return self._lines.stop_lines_m(vehicle_ids)


def quick_check(net_file: Path, additional: Path) -> str:
    """Run one simulated second on ``net_file``; returns SUMO's version string."""
    sim = Simulation(SumoOptions(net_file, (additional,), 0.1, 0))
    for _ in range(10):
        sim.step()
    t = sim.time_s()
    version = libsumo.getVersion()[1]
    sim.close()
    if abs(t - 1.0) > 1e-9:
        raise UserError(f"SUMO ran to t = {t} s instead of 1 s")
    return str(version)

"""Who drives in a deployment: drivers the ground truth's run loops call before every step.

A driver (``sumo.simulation.Driver``) reads the live SUMO state it needs and drives the
vehicles of the driven population, the others keep their own SUMO models:

* on a section (``SectionDriver`` and its subclasses) the population is every vehicle that
  is not instrumented (``truth.section.is_instrumented``; where each snapshot hides its
  own vehicles, ``hidden = "snapshot"``, nobody is: ``deploy.population``), or a share of
  them drawn per vehicle by a hash, or one vType; each is driven from the step it is on a lane of the
  section until it leaves the section (the paper's ring: its whole fleet, or a share).

Two ways to drive: speed commands (``*SpeedDriver``: v + a dt with a from a batched action
function, for the learned policies) and a vType switch (``*TypeDriver``: SUMO's own model
with other parameters, for the IDM baselines and SUMO's defaults). The passive base classes
drive nobody: the oracle, which only counts. Every driver counts per run
(``deploy.population.DriveStats``): ``vehicle_steps_driven``, ``safety_acted`` (speed
commands the safety layer or SUMO lowered by more than 0.01 m/s), ``floor_acted`` (raised
to the safety layer's floor, ``deploy.safety``) and ``emergency_brakings`` (vehicle-steps,
all vehicles on the road, whose acceleration was below minus the decel of their own demand
vType by more than 0.01 m/s^2).
"""

from __future__ import annotations

import math
from functools import partial
from itertools import compress, filterfalse, repeat
from operator import and_

import numpy as np

from macromicro_sumo.deploy.brake_plan import BrakeHandover, planned_decel
from macromicro_sumo.deploy.keep_clear import keep_clear_lines
from macromicro_sumo.deploy.keep_right import keep_right_caps
from macromicro_sumo.deploy.merge_yield import LANE_END_RECHECK_STEPS, MergeYield, drop_chain_lanes
from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table, observe_rows, states_of
from macromicro_sumo.deploy.population import ActionBatch, DriveStats, in_share
from macromicro_sumo.deploy.safety import (
    SAFETY_TOLERANCE_MPS,
    SPEED_MODES,
    leader_safe_speed,
    speed_commands,
)
from macromicro_sumo.deploy.slots import NOT_ASKED, VehicleSlots
from macromicro_sumo.deploy.turn_gap import asked_lanes, turn_gap_caps
from macromicro_sumo.deploy.turns import Turns
from macromicro_sumo.road.leaders import stop_distance_m
from macromicro_sumo.road.physics import count_nonzero
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section
from macromicro_sumo.road.vtype import VTypePhysics, read_vtype
from macromicro_sumo.sumo.signal_reach import signal_lanes
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates
from macromicro_sumo.truth.section import is_instrumented

BRAKING_TOLERANCE_MPS2 = 0.01
# 0-d arrays: no conversion of a Python float a step (``deploy.observe._const``)
_SAFETY_TOLERANCE, _INF = np.array(SAFETY_TOLERANCE_MPS), np.array(np.inf)


# --------------------------------------------------------------------------- sections


class SectionDriver:
    """Drives nobody (the oracle); keeps track of the population on the section and counts."""

    drives = False  # the oracle's vehicles are SUMO's: none counts as driven

    def __init__(self, sc, section: Section, run: int) -> None:
        self.sc, self.section, self.run = sc, section, run
        self.stats = DriveStats()
        self.types: dict[str, str] = {}  # vehicle -> its demand vType
        self.population: set[str] = set()  # vehicles this method may drive
        self.driven: set[str] = set()  # driven now (on the section)
        self.vtypes: dict[str, VTypePhysics] = {}  # demand vType -> its record, read once
        # Per vehicle, what the hot paths look up of its vType's record: (length, minGap,
        # decel) and decel.
        self.shape_of: dict[str, tuple[float, float, float]] = {}
        self.decel_of: dict[str, float] = {}
        # shape_of and section.lanes as numpy tables (``deploy.observe``), built once a run
        self.shape_table = Table(STANDING)
        self.type_code: dict[str, int] = {}  # vType -> its row in shape_table
        self.lane_table = LaneTable(section)
        self.steps = 0
        # The last ``before_step``'s states, per vehicle on a section lane and in the population
        self.flags: tuple[VehicleStates | None, list[bool], list[bool]] = (None, [], [])
        self.at_rows: tuple[list[str], np.ndarray, list[str]] = ([], np.empty(0, np.int64), [])
        self._brake_limit: tuple[tuple[str, ...], np.ndarray] = ((), np.empty(0))
        # -decel - tolerance of the least decel among the vTypes met: the loosest threshold.
        # A numpy 0-d array: compared every step without numpy's conversion of a float.
        self._loosest_brake = np.array(-np.inf)

    def before_step(self, sim: Simulation) -> None:
        self.steps += 1
        # The state after the last step, read once and shared with the recorder.
        st = sim.vehicle_states()
        # Every vehicle on the road this driver has not met yet, not only those SUMO lists
        # as departed in the last step: on a closed section cars that loop for the whole
        # run (rerouters) departed once, and a departure this driver did not see (before
        # it was attached, or a list read by someone else) must not leave them undriven.
        ids = st.ids
        new = list(filterfalse(self.types.__contains__, ids))  # SUMO's order, in C
        if new:
            self.arrive(sim, tuple(new))
        self.count_brakings(st)
        if not self.drives:  # the oracle: no hand-over, no count of driven vehicles
            return
        # In SUMO's order, which is sorted by ID (``VehicleStates``): no sort needed. C-level
        # passes, not a Python loop per vehicle.
        on = list(map(self.section.lanes.__contains__, st.lanes))
        ours = list(map(self.population.__contains__, ids))
        # Kept for this step's ``MergeYield.must_change``: those on the section and not ours
        # are the vehicles not driven there, without a second pass over every vehicle.
        self.flags = (st, on, ours)
        mask = list(map(and_, on, ours))
        vids = list(compress(ids, mask))
        now = set(vids)
        # Still in the network (on the road or teleporting), not on the section now: SUMO's
        # arrivals asked only where a driven vehicle is gone from the section.
        left = self.driven.difference(now)
        if left:
            left.difference_update(sim.arrived())
        if left:
            self.release(sim, sorted(left))
        entered = sorted(now - self.driven)
        if entered:
            self.take(sim, entered)
        self.driven = now
        self.stats.vehicle_steps_driven += len(now)
        if vids:  # ``drive``'s rows and lanes of this list by the mask, in C (no st.index)
            rows = np.fromiter(compress(range(len(ids)), mask), np.int64, len(vids))
            self.at_rows = (vids, rows, list(compress(st.lanes, mask)))
            self.drive(sim, vids, st)

    def arrive(self, sim: Simulation, new: tuple[str, ...]) -> None:
        dep = self.sc.deploy
        for vid in new:
            vt = sim.vehicle_type(vid)
            self.types[vid] = vt
            if vt not in self.vtypes:
                self.vtypes[vt] = read_vtype(sim, vt)
                self.type_code[vt] = self.shape_table.add_row(self.vtypes[vt].shape)
                least = min(p.decel_mps2 for p in self.vtypes.values())
                self._loosest_brake = np.array(-least - BRAKING_TOLERANCE_MPS2)
            self.shape_of[vid] = self.vtypes[vt].shape
            self.decel_of[vid] = self.vtypes[vt].decel_mps2
            self.shape_table.code[vid] = self.type_code[vt]
            if is_instrumented(self.sc, vid, vt, self.run):
                continue
            if dep.vtype and vt != dep.vtype:
                continue
            if in_share(self.sc.seed, self.run, vid, dep.share):
                self.population.add(vid)

    def count_brakings(self, st: VehicleStates) -> None:
        """Vehicles on the road braking harder than their demand vType's decel (one
        teleporting is not on the road: SUMO's acceleration of it is a placeholder)."""
        n = len(st.ids)
        # Nobody below the loosest threshold (that of the least decel met; rounding is
        # monotonic): nobody below their own, and no per-vehicle thresholds a step.
        if not n or not count_nonzero(st.accel_mps2 < self._loosest_brake):
            return
        # The decel of the vehicle's own demand vType, whatever it drives with now, as the
        # threshold -decel - tolerance; kept while the vehicles on the road are the same.
        ids, limit = self._brake_limit
        if st.ids != ids:
            decel = np.fromiter(map(self.decel_of.get, st.ids, repeat(np.inf)), float, n)
            limit = -decel - BRAKING_TOLERANCE_MPS2
            self._brake_limit = (st.ids, limit)
        self.stats.emergency_brakings += int(count_nonzero(st.accel_mps2 < limit))

    def take(self, sim: Simulation, vids: list[str]) -> None:
        """Vehicles that entered the section (or the population's drive) this step."""

    def release(self, sim: Simulation, vids: list[str]) -> None:
        """Vehicles that left the section: back to their own model."""

    def drive(self, sim: Simulation, vids: list[str], st: VehicleStates) -> None:
        """Act on the vehicles driven now (sorted; on the road: in ``st``), before the step."""


class SectionSpeedDriver(MergeYield, SectionDriver):
    """Speed commands from ``act`` for every driven vehicle, one batched call per step."""

    drives = True

    def __init__(self, sc, section: Section, run: int, act: ActionBatch, safety: str) -> None:
        super().__init__(sc, section, run)
        self.act = act
        self.safety = safety
        self.mode = SPEED_MODES[safety]
        # deploy.safety "sumo": a driver's planned braking handed over from its arrival
        dt = sc.simulation.step_length_s
        self.brake_handover = BrakeHandover(dt) if safety == "sumo" else None
        self.has_lights: bool | None = None
        self.signal_lanes: frozenset[str] = frozenset()  # lanes that can have one ahead
        # Per driven vehicle, in numpy arrays by slot: the last command and the caches of
        # SUMO's best lanes (where it must have left its lane) and of its signals ahead.
        self.slots = VehicleSlots()
        self.merge = sc.deploy.merge  # "none", "handover" or "sumo" (with the yield)
        make = getattr(act, "driver_speeds", None)  # policy.driver_speed: each driver's factor
        self.driver_speeds = make(sc, run) if make is not None else None
        taus = getattr(act, "driver_taus", None)  # policy.driver_follow: each driver's tau
        self.driver_taus = taus(sc, run) if taus is not None else None
        self.merging: set[str] = set()  # driven vehicles merging with SUMO's own model now
        self.others: set[str] = set()  # ``MergeYield.must_change``
        # deploy.merge_reach "occupation", with merge "sumo": LC2013's lane drop (MergeYield)
        reach = sc.deploy.merge_reach == "occupation" and self.merge == "sumo"
        self.occupation = self.yield_all = reach
        if reach:  # the lanes occupation acts on, once per driver
            self.drop_lanes = drop_chain_lanes(section)
        # deploy.turns: the turners, their routes asked of SUMO on junction edges (built at
        # the first take, which knows the net file)
        self.turns_mode = sc.deploy.turns
        self.turns: Turns | None = None
        self.gap_lanes: frozenset[str] | None = None  # deploy.turn_gap's lanes to ask on

    def take(self, sim: Simulation, vids: list[str]) -> None:
        if self.turns_mode != "off" and self.turns is None:
            dt = self.sc.simulation.step_length_s
            self.turns = Turns(self.section, sim.options.net_file, dt)
        if self.gap_lanes is None:  # where a turner changes lanes, read from the net once
            on = self.sc.deploy.turn_gap == "sumo"
            net, occ = sim.options.net_file, self.occupation
            self.gap_lanes = asked_lanes(self.section, net, occ) if on else frozenset()
        sim.set_speed_mode(vids, self.mode)
        for v in vids:
            if v not in self.slots.of:
                self.slots.add(v)
        # A vehicle or two a step: scalar writes, the values four index writes from lists
        # wrote (2 vehicles: 0.9 against 8.0 us, numpy 2.4), after any growth of the arrays.
        s = self.slots
        for v in vids:
            i, p = s.of[v], self.vtypes[self.types[v]]
            s.decel[i] = self.decel_of[v]
            s.vmax[i] = p.max_speed_mps
            s.accel[i] = p.accel_mps2
            s.with_gap[i] = sum(self.shape_of[v][:2])

    def release(self, sim: Simulation, vids: list[str]) -> None:
        sim.release_speeds(vids)
        self.merging.difference_update(vids)
        self.slots.forget(vids)

    def slots_of(self, vids: list[str], lanes: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """(slots, lane codes in ``lane_table``) of driven vehicles ``vids`` on ``lanes``;
        a slot for any vehicle met without one (a caller observing vehicles it drives not)."""
        try:
            slots = self.slots.slots(vids)
        except KeyError:
            for v in vids:
                if v not in self.slots.of:
                    self.slots.add(v)
            slots = self.slots.slots(vids)
        return slots, self.lane_table.codes(lanes)

    def lane_end_m(self, sim: Simulation, vids: list[str], lanes: list[str],
                   at: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:  # fmt: skip
        """Per vehicle, the distance from its lane's start to where it must have left that
        lane (inf: the lane carries it on), from SUMO's best lanes: asked when a vehicle is
        on a lane for the first time, a lane that carries it on again after
        ``LANE_END_RECHECK_STEPS`` (one call per vehicle and step would cost more than
        SUMO's whole step). The one cache of SUMO's lane ends, per slot, the driven
        vehicles' and those ``MergeYield.must_change`` asks of (its ``offset``). ``at``:
        ``slots_of(vids, lanes)`` if known."""
        slots, codes = self.slots_of(vids, lanes) if at is None else at
        cache, now = self.slots.lane_end, self.steps
        due = cache.due(slots, codes, now)
        if due.size:
            # A few vehicles a step: scalar writes, not a dozen array calls for them.
            for i in due.tolist():
                end, offset = sim.lane_end(vids[i], lanes[i], 0.0)
                # A lane end, once seen, stays; a lane that carries the vehicle on is asked
                # again.
                again = now + LANE_END_RECHECK_STEPS if end == math.inf else math.inf
                cache.put(int(slots[i]), int(codes[i]), end, again, offset)
        return cache.value[slots]

    def stop_lines_m(self, sim: Simulation, vids: list[str], lanes: list[str],
                     at: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:  # fmt: skip
        """Per vehicle, ``Simulation.stop_lines_m`` (inf: no red or yellow ahead), asked
        only of vehicles that may meet a signal: one SUMO found none ahead of on its whole
        route is asked again when it changes lane or ``LANE_END_RECHECK_STEPS`` later (on
        Bremen's highway only the ramp has one: the call was a tenth of the driver), one
        with a signal ahead every step. ``at``: ``slots_of(vids, lanes)`` if known."""
        slots, codes = self.slots_of(vids, lanes) if at is None else at
        cache, now = self.slots.dark, self.steps
        due = cache.due(slots, codes, now)
        if due.size:
            idx, ask = [], self.signal_lanes.__contains__
            for i in due.tolist():  # on a lane that reaches no signal: NaN, for good
                if ask(lanes[i]):
                    idx.append(i)
                else:
                    cache.put(int(slots[i]), int(codes[i]), math.inf, math.inf)
            got = sim.stop_lines_m([vids[i] for i in idx]).tolist() if idx else []
            for i, d in zip(idx, got, strict=True):
                if d != d:  # NaN, no signal ahead: not asked again for a while
                    cache.put(int(slots[i]), int(codes[i]), math.inf, now + LANE_END_RECHECK_STEPS)
                else:
                    cache.put(int(slots[i]), NOT_ASKED, d, -math.inf)
        return cache.value[slots]  # inf where not due: dark

    def drive(self, sim: Simulation, vids: list[str], st: VehicleStates) -> None:
        held, rows, lanes = self.at_rows
        if held is not vids:  # not ``before_step``'s list (a subclass's own)
            rows = np.fromiter(map(st.index.__getitem__, vids), np.int64, len(vids))
            lanes = list(map(st.lanes.__getitem__, rows.tolist()))
        slots, codes = self.slots_of(vids, lanes)
        if self.turns_mode == "handover":  # turners near their line: SUMO's for good
            near = self.turns.to_hand(vids, self.lane_table, codes, rows, slots, st, self.slots)
            if near.size:
                gone = [vids[i] for i in near.tolist()]
                self.population.difference_update(gone)
                self.driven.difference_update(gone)
                self.release(sim, gone)
                idx = np.delete(np.arange(len(vids)), near)
                vids, lanes = [vids[i] for i in idx.tolist()], [lanes[i] for i in idx.tolist()]
                rows, slots, codes = rows[idx], slots[idx], codes[idx]
                if not vids:
                    return
        # Where each must have left its lane: the merges' hand-over and the observation's
        # standing leader, asked once.
        ahead = self.lane_end_m(sim, vids, lanes, (slots, codes)) - st.pos_m[rows]
        speed = st.speed_mps[rows]
        near: list[int] = []
        factor = None
        if self.driver_speeds is not None:  # a factor where first seen, handed over or not
            factor = self.slots.factor[slots]
            new = np.isnan(factor).nonzero()[0]
            if new.size:  # ``factors``, the rows of the new ones alone (its obs[new])
                fresh = [vids[i] for i in new.tolist()]
                # Their whole observation (what is ahead) for "memory" with
                # policy.driver_entry "held" (``held_at_sight``: the leader), or with a
                # driver's tau (``DriverTaus`` starts its hand-over from that observation);
                # "drawn", and "memory" "queued" alone, read only the speed and limit.
                ds = self.driver_speeds
                if ds.kind == "memory" and (ds.entry != "queued" or self.driver_taus is not None):
                    at = (slots[new], codes[new])
                    lane_of = [lanes[i] for i in new.tolist()]
                    one = np.ones(new.size)
                    seen = self.observe(
                        sim, fresh, rows[new], st, None, lane_of, ahead[new], at, one
                    )[0]
                elif ds.kind == "memory":  # the observation's speed and unscaled limit
                    seen = np.column_stack([speed[new], self.lane_table.limit_mps[codes[new]]])
                else:  # "drawn": a hash of the vehicle alone, no observation read
                    seen = None
                factor[new] = got = self.driver_speeds(fresh, seen)
                self.slots.factor[slots[new]] = got
        if self.merge != "none":
            keep = self.handed_over(sim, vids, ahead, rows, lanes, slots, speed, st)
            if keep is not None:
                # Indices, not the mask: a take by index costs a fraction of a masked one.
                idx = keep.nonzero()[0]
                listed = idx.tolist()
                vids, lanes = [vids[i] for i in listed], [lanes[i] for i in listed]
                rows, ahead, slots, codes = rows[idx], ahead[idx], slots[idx], codes[idx]
                speed = speed[idx]
                factor = None if factor is None else factor[idx]
                if not vids:
                    return
            near = self.blocking(sim, vids, slots, st)
        # Last step's command against the speed SUMO applied (-inf: none to compare with).
        self.stats.safety_acted += int(
            count_nonzero(speed < self.slots.last_mps[slots] - _SAFETY_TOLERANCE)
        )
        if self.has_lights is None:
            self.has_lights = sim.has_traffic_lights()
            if self.has_lights:
                self.signal_lanes = signal_lanes(sim.options.net_file)
                if self.sc.deploy.yellow != "stop":  # SUMO's yellow rule, decided at onset
                    sim.decide_yellow(ahead=self.sc.deploy.yellow == "ahead")
        obs, gap, lead_decel, lead = self.observe(
            sim, vids, rows, st, lanes=lanes, stop_m=ahead, at=(slots, codes), factor=factor
        )
        # One leader table a step: the safe speed behind what each sees ahead, for both the
        # merges' yield and the safety layer.
        own = safe = cap = lead_speed = None
        if near or self.safety == "sumo":
            own = planned_decel(self.slots.decel[slots], lead_decel, self.sc.deploy.safety_brake)
            lead_speed = obs[:, 0] - obs[:, 3]
            if self.brake_handover is not None:  # a new driver's braking from its arrival
                own = self.brake_handover(
                    slots, own, lead_decel, gap, obs[:, 0], lead_speed, self.steps
                )
            dt = self.sc.simulation.step_length_s
            safe = leader_safe_speed(obs, gap, own, lead_decel, dt, lead_speed, self.red_gap_m)
        if near:
            cap = self.yields(sim, vids, near, obs[:, 0], safe)
        # LC2013's speed requests a command overrides: a gap to change into, no passing right.
        cap = turn_gap_caps(self.sc, self.section, self.shape_of, st, rows, cap, self.gap_lanes)
        cap = keep_right_caps(self.sc, self.section, self.shape_of, st, rows, cap)

        def layer() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            return gap, own, lead_decel, lead

        # The vType's maxSpeed and accel are the vehicle's physics, not safety: SUMO does not
        # impose them on a command under these speed modes (no max-accel bit; ring_two_lane's
        # vans, maxSpeed 12, ran at up to 14.9 m/s; drawn net 300's trucks, accel 1.0, at up
        # to the bound's 2.6 m/s^2): every command is held to them, with or without the layer.
        cmd = speed_commands(
            self.sc,
            self.act,
            self.safety,
            self.stats,
            obs,
            layer,
            cap,
            safe,
            lead_speed,
            self.slots.vmax[slots],
            self.slots.accel[slots],
            bool(self.has_lights),  # deploy.command_dawdle = "signals"
        )
        sim.set_speeds(vids, cmd)
        self.slots.commanded(slots, cmd)

    def factors(
        self, slots: np.ndarray, vids: list[str], obs: np.ndarray, known: np.ndarray | None = None
    ) -> np.ndarray:
        """``policy.driver_speed``: the factors of driven vehicles ``vids`` (slots
        ``slots``, observations ``obs`` with unscaled limits), kept per slot: the driver's
        ``DriverSpeeds`` asked only of a vehicle met for the first time; ``known``: these
        factors, read already (none new)."""
        if known is not None:
            return known
        f = self.slots.factor[slots]
        new = np.isnan(f).nonzero()[0]
        if new.size:
            got = self.driver_speeds([vids[i] for i in new.tolist()], obs[new])
            f[new] = got
            self.slots.factor[slots[new]] = got
        return f

    def observe(
        self,
        sim: Simulation,
        vids: list[str],
        rows: np.ndarray,
        st: VehicleStates,
        shapes: Table | None = None,
        lanes: list[str] | None = None,
        stop_m: np.ndarray | None = None,
        at: tuple[np.ndarray, np.ndarray] | None = None,
        factor: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``observe_rows`` of driven vehicles ``vids`` (rows ``rows`` of ``st``): SUMO's
        leaders, lane ends and red lights asked now; ``shapes``: vehicle -> (length,
        minGap, decel) (default: the vTypes of the vehicles this driver saw arrive);
        ``lanes``, ``stop_m``: their lanes and the distances to those lanes' ends if
        known already (``lane_end_m`` minus the position); ``at``: ``slots_of``;
        ``factor``: their drivers' factors (``factors``) if known already."""
        if lanes is None:
            lanes = list(map(st.lanes.__getitem__, rows.tolist()))
        if at is None:
            at = self.slots_of(vids, lanes)
        if stop_m is None:
            stop_m = self.lane_end_m(sim, vids, lanes, at) - st.pos_m[rows]
        self.red_gap_m = None  # SUMO's gap to each one's red line (inf: none), for ``drive``
        # Nobody on a lane reaching a signal: none ahead (NaN; inf in the cache), not asked.
        leaders = sim.leaders(vids, NO_LEADER_GAP_M)
        if self.has_lights and not self.signal_lanes.isdisjoint(lanes):
            red = self.stop_lines_m(sim, vids, lanes, at)
            red = keep_clear_lines(self, sim, red, lanes, rows, st, leaders, vids)
            # No red or yellow ahead of anyone (inf): the stops are the lane ends as they are.
            if count_nonzero(red < _INF):
                gaps = np.array([self.vtypes[self.types[v]].stopline_gap_m for v in vids])
                stop_m = stop_distance_m(stop_m, red, gaps)  # gaps: jmStoplineGap
                self.red_gap_m = stop_distance_m(_INF, red, gaps)
        return observe_rows(
            self.lane_table,
            self.sc.policy.observation,
            vids,
            rows,
            lanes,
            st,
            leaders,
            self.shape_table if shapes is None else shapes,
            stop_m,
            None if self.driver_speeds is None else partial(self.factors, at[0], known=factor),
            at[1],
            # Its prior's minGap where no layer holds the vType's (observe_rows' stop_gap_m).
            getattr(self.act, "stop_gap_m", None) if self.safety == "none" else None,
            None if self.driver_taus is None else partial(self.driver_taus, step=self.steps),
            self.turns.ahead(vids, self.lane_table, at[1], st.pos_m[rows])
            if self.turns is not None and self.turns_mode == "limit"
            else None,
        )


def section_observations(
    drv: SectionSpeedDriver, sim: Simulation, vids: list[str], states: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``SectionSpeedDriver.observe`` of ``vids`` from a {vehicle: (lane ID, lane position,
    speed, acceleration)} dictionary of the vehicles on the road (the demand env's): the
    observations, SUMO's gaps and the leaders' decels."""
    st = states_of(states)
    rows = np.fromiter(map(st.index.__getitem__, vids), np.int64, len(vids))
    return drv.observe(sim, vids, rows, st, Table.of_rows(drv.shape_of, STANDING))[:3]

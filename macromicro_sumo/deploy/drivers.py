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

The parts: ``deploy.section_driver`` (``SectionDriver``: the population, each vehicle's vType
met at its first sight, the counts), ``deploy.lane_asks`` (SUMO's lane ends and stop lines,
cached per slot), ``deploy.driver_observe`` (the observation, the keep_clear lines, the
drivers' speed factors at first sight); here the speed driver's hand-over and its step
(``SectionSpeedDriver.drive``: the merges, the safety layer and the commands).
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.deploy.brake_plan import BrakeHandover, planned_decel
from macromicro_sumo.deploy.driver_observe import DriverObserve, section_observations
from macromicro_sumo.deploy.keep_clear import KeepClear
from macromicro_sumo.deploy.keep_right import keep_right_caps
from macromicro_sumo.deploy.lane_asks import LaneAsks
from macromicro_sumo.deploy.merge_yield import MergeYield, drop_chain_lanes
from macromicro_sumo.deploy.population import ActionBatch
from macromicro_sumo.deploy.safety import (
    SAFETY_TOLERANCE_MPS,
    SPEED_MODES,
    leader_safe_speed,
    speed_commands,
)
from macromicro_sumo.deploy.section_driver import BRAKING_TOLERANCE_MPS2, SectionDriver
from macromicro_sumo.deploy.slots import VehicleSlots
from macromicro_sumo.deploy.turn_gap import asked_lanes, turn_gap_caps
from macromicro_sumo.deploy.turns import Turns
from macromicro_sumo.road.physics import count_nonzero
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.signal_reach import signal_lanes
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates

# Importable from here as before the split (scripts and tests patch and read them here).
__all__ = [
    "BRAKING_TOLERANCE_MPS2",
    "ActionBatch",
    "SectionDriver",
    "SectionSpeedDriver",
    "VehicleSlots",
    "section_observations",
]

# 0-d array: no conversion of a Python float a step (``deploy.observe._const``)
_SAFETY_TOLERANCE = np.array(SAFETY_TOLERANCE_MPS)


class SectionSpeedDriver(DriverObserve, LaneAsks, MergeYield, SectionDriver):
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
        kc = sc.deploy.keep_clear  # its holds and the vehicles' shapes, for this driver
        self.keep_clear = None if kc == "off" else KeepClear(kc, section, dt)

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
            factor = self.first_sight(sim, vids, rows, st, lanes, slots, codes, ahead, speed)
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
                    sim.decide_yellow(
                        self.sc.deploy.yellow == "ahead", self.sc.deploy.yellow == "sumo"
                    )
                if self.sc.deploy.green == "switch":  # a green met in the step it comes
                    sim.decide_green()
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
            self.start_on(lanes),
        )
        sim.set_speeds(vids, cmd)
        self.slots.commanded(slots, cmd)

    def start_on(self, lanes: list[str]) -> np.ndarray | None:
        """``deploy.start_rules`` "signal_lanes": per driven vehicle, whether its lane can have
        a signal ahead (the start rules apply to it); None: all (the rules apply to all)."""
        if self.sc.deploy.start_rules == "all":
            return None
        if not self.signal_lanes:  # no light, or none reached from the section: nobody
            return np.zeros(len(lanes), bool)
        return np.fromiter(map(self.signal_lanes.__contains__, lanes), bool, len(lanes))

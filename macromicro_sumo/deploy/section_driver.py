"""The section driver's bookkeeping, the base of every driver (``deploy.drivers``): who is on
the section and in the driven population, each vehicle's demand vType and its shape as met at
its first sight (``arrive``), the hand-over at the section's edges (``take``, ``release``)
and the per-run counts (``deploy.population.DriveStats``), emergency brakings among them
(vehicle-steps, all vehicles on the road, whose acceleration was below minus the decel of
their own demand vType by more than ``BRAKING_TOLERANCE_MPS2``). ``SectionDriver`` itself
drives nobody: the oracle, which only counts.
"""

from __future__ import annotations

from itertools import compress, filterfalse, repeat
from operator import and_

import numpy as np

from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table
from macromicro_sumo.deploy.population import DriveStats, in_share
from macromicro_sumo.road.physics import count_nonzero
from macromicro_sumo.road.section import Section
from macromicro_sumo.road.vtype import VTypePhysics, read_vtype
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates
from macromicro_sumo.truth.section import is_instrumented

BRAKING_TOLERANCE_MPS2 = 0.01


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

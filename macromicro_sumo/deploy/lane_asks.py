"""What a speed driver (``deploy.drivers.SectionSpeedDriver``) asks SUMO of each driven
vehicle's lane, cached per vehicle slot (``deploy.slots.VehicleSlots``) because one call per
vehicle and step would cost more than SUMO's whole step: where it must have left its lane
(SUMO's best lanes, ``lane_end_m``) and its next red or yellow line (``stop_lines_m``).
"""

from __future__ import annotations

import math

import numpy as np

from macromicro_sumo.deploy.merge_yield import LANE_END_RECHECK_STEPS
from macromicro_sumo.deploy.observe import LaneTable
from macromicro_sumo.deploy.slots import NOT_ASKED, VehicleSlots
from macromicro_sumo.sumo.simulation import Simulation


class LaneAsks:
    """Mixed into ``SectionSpeedDriver``: the slots and lane codes of driven vehicles and
    SUMO's lane ends and stop lines, each asked only when due."""

    slots: VehicleSlots
    lane_table: LaneTable
    signal_lanes: frozenset[str]  # lanes that can have a signal ahead
    steps: int

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

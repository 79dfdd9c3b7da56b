"""What a speed driver (``deploy.drivers.SectionSpeedDriver``) observes of the vehicles it
drives: ``deploy.observe.observe_rows`` with SUMO's leaders asked now, the stops ahead (lane
ends, red and yellow lines, ``deploy.keep_clear``'s lines) and each driver's
``policy.driver_speed`` factor, drawn at the vehicle's first sight (``first_sight``).
"""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np

from macromicro_sumo.deploy.keep_clear import KeepClear
from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table, observe_rows, states_of
from macromicro_sumo.deploy.slots import VehicleSlots
from macromicro_sumo.road.leaders import stop_distance_m
from macromicro_sumo.road.physics import count_nonzero
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.road.vtype import VTypePhysics
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates

# 0-d array: no conversion of a Python float a step (``deploy.observe._const``)
_INF = np.array(np.inf)


class DriverObserve:
    """Mixed into ``SectionSpeedDriver`` (with ``deploy.lane_asks.LaneAsks``): its
    observation of the driven vehicles and their drivers' speed factors."""

    sc: Any  # the section scenario
    act: Any  # the batched action function (``deploy.population.ActionBatch``)
    safety: str
    slots: VehicleSlots
    lane_table: LaneTable
    shape_table: Table
    shape_of: dict[str, tuple[float, float, float]]
    vtypes: dict[str, VTypePhysics]
    types: dict[str, str]
    driver_speeds: Any  # ``policy.driver_speed``'s ``DriverSpeeds``, or None
    driver_taus: Any  # ``policy.driver_follow``'s ``DriverTaus``, or None
    has_lights: bool | None
    signal_lanes: frozenset[str]
    turns: Any  # ``deploy.turns.Turns``, or None
    turns_mode: str
    keep_clear: KeepClear | None
    steps: int
    red_gap_m: np.ndarray | None

    def first_sight(
        self,
        sim: Simulation,
        vids: list[str],
        rows: np.ndarray,
        st: VehicleStates,
        lanes: list[str],
        slots: np.ndarray,
        codes: np.ndarray,
        ahead: np.ndarray,
        speed: np.ndarray,
    ) -> np.ndarray:
        """``policy.driver_speed``: the factors of driven vehicles ``vids`` (rows ``rows`` of
        ``st``, on ``lanes``, slots ``slots``, lane codes ``codes``, ``ahead`` [m] to their
        lanes' ends, speeds ``speed``), each drawn where the vehicle is first seen, handed
        over or not, and kept in its slot."""
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
                got = self.observe(sim, fresh, rows[new], st, None, lane_of, ahead[new], at, one)
                seen = got[0]
            elif ds.kind == "memory":  # the observation's speed and unscaled limit
                seen = np.column_stack([speed[new], self.lane_table.limit_mps[codes[new]]])
            else:  # "drawn": a hash of the vehicle alone, no observation read
                seen = None
            factor[new] = got = self.driver_speeds(fresh, seen)
            self.slots.factor[slots[new]] = got
        return factor

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
            if self.keep_clear is not None:  # deploy.keep_clear: a line where it cannot clear
                net, shapes_of = sim.options.net_file, self.shape_of
                red = self.keep_clear.lines(net, red, lanes, rows, st, leaders, vids, shapes_of)
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
    drv: DriverObserve, sim: Simulation, vids: list[str], states: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``SectionSpeedDriver.observe`` of ``vids`` from a {vehicle: (lane ID, lane position,
    speed, acceleration)} dictionary of the vehicles on the road (the demand env's): the
    observations, SUMO's gaps and the leaders' decels."""
    st = states_of(states)
    rows = np.fromiter(map(st.index.__getitem__, vids), np.int64, len(vids))
    return drv.observe(sim, vids, rows, st, Table.of_rows(drv.shape_of, STANDING))[:3]

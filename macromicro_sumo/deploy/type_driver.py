"""The vType-switching driver of a section (``deploy.drivers``' other way to drive): the
driven vehicles keep SUMO's own model, with another vType's parameters while on the
section (the IDM baselines and SUMO's defaults)."""

from __future__ import annotations

import numpy as np

from macromicro_sumo.deploy.drivers import SectionDriver
from macromicro_sumo.deploy.population import SwitchedType
from macromicro_sumo.road.physics import safe_speed
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates


class SectionTypeDriver(SectionDriver):
    """Driven vehicles switched to another vType while on the section (SUMO drives them
    with that vType's model and parameters), switched back when they leave it.

    A vType is changed only where the vehicle's next vType fits behind its leader: a
    bumper gap of at least its minGap, and a speed its model can bring down to the safe
    speed with its own decel (``fits``). SUMO registers a collision wherever a gap falls
    below the follower's minGap: on Spreewaldring the race cars (minGap 0) queue at the
    start 0.1 m apart, and switched there to SUMO's defaults (minGap 2.5 m) every one of
    them was in collision with its leader until the queue moved (26 collisions a run).
    A vehicle waits on the section in its own vType (not counted as driven), or past the
    section's end in the switched one, until the other fits."""

    drives = True

    def __init__(self, sc, section: Section, run: int, switch: SwitchedType) -> None:
        super().__init__(sc, section, run)
        self.switch = switch
        self.own_factor: dict[str, float] = {}
        self.factor: dict[str, float] = {}  # one draw per vehicle, kept on re-entry
        self.waiting: set[str] = set()  # on the section, not switched yet
        self.leaving: set[str] = set()  # off the section, not switched back yet
        self.new_shapes: dict[str, tuple[float, float, float]] = {}  # switched vType's

    def before_step(self, sim: Simulation) -> None:
        super().before_step(sim)
        if self.leaving:
            st = sim.vehicle_states()
            # Gone (arrived) or teleporting: nothing to fit behind now.
            here = sorted(v for v in self.leaving if v in st.index)
            own = [self.shape_of[v] for v in here]
            now = [self.switched_shape(sim, v) for v in here]
            ok = self.fits(sim, here, st, own, now)
            ready = [v for v, fit in zip(here, ok, strict=True) if fit]
            if ready:
                self.switch_back(sim, ready)
            self.leaving.difference_update(ready)
            self.leaving.intersection_update(sim.vehicle_ids())

    def take(self, sim: Simulation, vids: list[str]) -> None:
        back = self.leaving.intersection(vids)  # still in the switched vType
        self.leaving.difference_update(back)
        self.waiting.update(v for v in vids if v not in back)

    def drive(self, sim: Simulation, vids: list[str], st: VehicleStates) -> None:
        if self.waiting:
            cands = sorted(self.waiting)
            new = [self.switched_shape(sim, v) for v in cands]
            ok = self.fits(sim, cands, st, new, [self.shape_of[v] for v in cands])
            ready = [v for v, fit in zip(cands, ok, strict=True) if fit]
            if ready:
                self.switch_to_new(sim, ready)
                self.waiting.difference_update(ready)
        self.stats.vehicle_steps_driven -= len(self.waiting)

    def switched_shape(self, sim: Simulation, vid: str) -> tuple[float, float, float]:
        """(length, minGap, decel) of the vType ``vid`` is switched to."""
        new = self.switch.type_of[self.types[vid]]
        if new not in self.new_shapes:
            self.new_shapes[new] = sim.vtype_shape(new)
        return self.new_shapes[new]

    def fits(
        self,
        sim: Simulation,
        vids: list[str],
        st: VehicleStates,
        shapes: list[tuple[float, float, float]],
        now: list[tuple[float, float, float]],
    ) -> np.ndarray:
        """Per vehicle, whether a vType of shape (length, minGap, decel) ``shapes`` fits
        behind its leader now (``now``: the shape of the vType it has): bumper gap >= its minGap, and a speed v with v - b dt <=
        ``safe_speed`` behind the leader (b its decel, the leader's taken as at least b):
        SUMO's model then follows without braking beyond b, nor into its minGap."""
        if not vids:
            return np.zeros(0, dtype=bool)
        new_gap, new_b = np.array(shapes, dtype=float).reshape(-1, 3)[:, 1:].T
        leaders = sim.leaders(vids, NO_LEADER_GAP_M)
        index = st.index
        lead_row = np.array([index.get(lid, -1) for lid, _ in leaders], dtype=np.int64)
        has = lead_row >= 0
        # SUMO's gap is measured to the vehicle's present minGap: the bumper gap is more.
        now_gap = np.array([shape[1] for shape in now])
        bumper = np.array([g for _, g in leaders]) + now_gap
        rows = np.fromiter(map(index.__getitem__, vids), np.int64, len(vids))
        v = st.speed_mps[rows]
        v_l = np.where(has, st.speed_mps[lead_row], 0.0)
        dt = self.sc.simulation.step_length_s
        safe = safe_speed(bumper - new_gap, v_l, new_b, new_b, dt)
        return ~has | ((bumper >= new_gap) & (v - new_b * dt <= safe))

    def switch_to_new(self, sim: Simulation, vids: list[str]) -> None:
        own = sim.speed_factors(vids)
        fresh = [v for v in vids if v not in self.factor]
        self.factor.update(zip(fresh, self.switch.factors(len(fresh)).tolist(), strict=True))
        self.own_factor.update(zip(vids, own.tolist(), strict=True))
        sim.set_types(vids, [self.switch.type_of[self.types[v]] for v in vids])
        sim.set_speed_factors(vids, [self.factor[v] for v in vids])

    def switch_back(self, sim: Simulation, vids: list[str]) -> None:
        sim.set_types(vids, [self.types[v] for v in vids])
        sim.set_speed_factors(vids, [self.own_factor[v] for v in vids])

    def release(self, sim: Simulation, vids: list[str]) -> None:
        switched = [v for v in vids if v not in self.waiting]
        self.waiting.difference_update(vids)
        self.leaving.update(switched)  # switched back in ``before_step`` once it fits

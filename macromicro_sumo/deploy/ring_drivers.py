"""The ring's drivers of a deployment (``deploy.drivers`` has the sections' and says what a
driver does): the population is the ring's fleet, or a share of it, driven for the whole
run. Speed commands see what the ring env's policies were trained on: leaders and
spacings from arc positions around the ring, the look-ahead to the next edge
(``env.ring``); the command rule is the sections' (``deploy.safety.speed_commands``).
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.deploy.drivers import BRAKING_TOLERANCE_MPS2
from macromicro_sumo.deploy.population import ActionBatch, DriveStats, SwitchedType, in_share
from macromicro_sumo.deploy.safety import SAFETY_TOLERANCE_MPS, SPEED_MODES, speed_commands
from macromicro_sumo.road.physics import lookahead_features, ring_leaders
from macromicro_sumo.road.ring import RingGeometry
from macromicro_sumo.sumo.simulation import Simulation


class RingDriver:
    """Drives nobody on the ring (the oracle); counts emergency brakings of the fleet."""

    drives = False

    def __init__(
        self,
        sc,
        geo: RingGeometry,
        run: int,
        ids: list[str],
        limits_mps: np.ndarray,
        decel: np.ndarray,
    ) -> None:
        self.sc, self.geo, self.ids = sc, geo, ids
        self.limits = limits_mps
        self.decel = decel
        self.edge_index = {e: i for i, e in enumerate(geo.edge_ids)}
        share = sc.deploy.share
        self.mask = np.array([in_share(sc.seed, run, v, share) for v in ids], dtype=bool)
        self.driven = [v for v, m in zip(ids, self.mask, strict=True) if m]
        self.stats = DriveStats()
        self.prev_speed: np.ndarray | None = None
        self.started = False

    def before_step(self, sim: Simulation) -> None:
        e, p, v = sim.read_states(self.ids, self.edge_index)
        if self.prev_speed is not None:
            a = (v - self.prev_speed) / self.sc.simulation.step_length_s
            self.stats.emergency_brakings += int((a < -self.decel - BRAKING_TOLERANCE_MPS2).sum())
        self.prev_speed = v
        if not self.started:
            self.started = True
            self.take(sim)
        self.stats.vehicle_steps_driven += len(self.driven) if self.drives else 0
        self.drive(sim, self.geo.offsets_m[e] + p, v, e)

    def take(self, sim: Simulation) -> None:
        """The driven vehicles, before the first driven step."""

    def drive(self, sim: Simulation, arc: np.ndarray, speed: np.ndarray, edge: np.ndarray) -> None:
        """Act on the driven vehicles, before the step."""


class RingSpeedDriver(RingDriver):
    """Speed commands from ``act``; observations as the ring env's (``env.ring``): leaders
    and spacings from arc positions around the ring, lookahead to the next edge."""

    drives = True

    def __init__(
        self, *args, act: ActionBatch, safety: str, length: np.ndarray, min_gap: np.ndarray
    ) -> None:
        super().__init__(*args)
        self.act = act
        self.safety = safety
        self.length, self.min_gap = length, min_gap
        self.mode = SPEED_MODES[safety]
        self.commands: np.ndarray | None = None

    def take(self, sim: Simulation) -> None:
        sim.set_speed_mode(self.driven, self.mode)

    def drive(self, sim: Simulation, arc: np.ndarray, speed: np.ndarray, edge: np.ndarray) -> None:
        m = self.mask
        if self.commands is not None:
            self.stats.safety_acted += int((speed[m] < self.commands - SAFETY_TOLERANCE_MPS).sum())
        full = ring_observations(self, arc, speed, edge)
        obs = full[m]

        def layer() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            leader, _ = ring_leaders(np.mod(arc, self.geo.length_m), self.geo.length_m)
            gap = obs[:, 2] - self.length[leader[m]] - self.min_gap[m]
            # Each driven vehicle's leader among the driven (-1: SUMO drives it).
            driven_index = np.full(len(m), -1)
            driven_index[m] = np.arange(int(m.sum()))
            return gap, self.decel[m], self.decel[leader[m]], driven_index[leader[m]]

        cmd = speed_commands(self.sc, self.act, self.safety, self.stats, obs, layer)
        self.commands = cmd
        sim.set_speeds(self.driven, self.commands)


def ring_observations(
    drv: RingDriver, arc: np.ndarray, speed: np.ndarray, edge: np.ndarray
) -> np.ndarray:
    """Every vehicle's [v, v_limit, spacing, v - v_leader] (+ lookahead), as the ring env."""
    geo = drv.geo
    arc = np.mod(arc, geo.length_m)
    leader, spacing = ring_leaders(arc, geo.length_m)
    cols = [speed, drv.limits[edge], spacing, speed - speed[leader]]
    if drv.sc.policy.observation == "lookahead":
        cols += list(lookahead_features(arc, edge, geo.offsets_m, geo.lengths_m, drv.limits))
    return np.stack(cols, axis=1)


class RingTypeDriver(RingDriver):
    """The driven vehicles switched to another vType for the whole run."""

    drives = True

    def __init__(self, *args, switch: SwitchedType) -> None:
        super().__init__(*args)
        self.switch = switch

    def take(self, sim: Simulation) -> None:
        sim.set_types(self.driven, [self.switch.type_of["fleet"]] * len(self.driven))
        sim.set_speed_factors(self.driven, self.switch.factors(len(self.driven)))

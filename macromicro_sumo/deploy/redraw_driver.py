"""The population oracle's driver: every vehicle of the driven population keeps its true
model, but its own draws are redrawn from the population it came from, once, when it
appears. What a perfect model of the population that knows nothing of each driver
reaches: no loop or observed vehicle gives a hidden driver's own parameters (a policy that
reads a driver's own speed, ``policy.driver_speed = "memory"``, knows some of it;
docs/deploy-log.md, "What a near-exact model reaches").

* a fleet (the paper's ring): the driver's accel, decel, tau, minGap and speedFactor, each
  uniform in the ``[fleet]`` table's range, as the truth drew them;
* a user's demand: the vehicle's speedFactor, normal around its vType's mean with its
  vType's deviation, kept in SUMO's default bounds [0.2, 2] (a vType's own bounds are not
  read through libsumo); a vType without deviation is left as it is.
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.deploy.drivers import SectionDriver
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.fleet import fleet_demand
from macromicro_sumo.sumo.simulation import Simulation

SPEED_FACTOR_BOUNDS = (0.2, 2.0)  # SUMO's default cut of a vType's speedFactor draw
# (SUMO's parameter name, the [fleet] range it is drawn from)
FLEET_PARAMS = (
    ("accel", "accel_mps2"),
    ("decel", "decel_mps2"),
    ("tau", "tau_s"),
    ("minGap", "min_gap_m"),
    ("speedFactor", "speed_factor"),
)


class SectionRedrawDriver(SectionDriver):
    """Drives nobody; redraws each population vehicle's own parameters when it appears."""

    def __init__(self, sc, section: Section, run: int, rng: np.random.Generator) -> None:
        super().__init__(sc, section, run)
        self.rng = rng
        demand = fleet_demand(sc)
        self.fleet = demand.fleet if demand is not None else None

    def arrive(self, sim: Simulation, new: tuple[str, ...]) -> None:
        super().arrive(sim, new)
        for vid in new:  # SUMO's order (sorted IDs): the draws repeat with the seed
            if vid not in self.population:
                continue
            if self.fleet is not None:
                draws = {
                    name: self.rng.uniform(*getattr(self.fleet, key)) for name, key in FLEET_PARAMS
                }
            else:
                mean, dev = sim.vtype_speed_factor(self.types[vid])
                if dev <= 0.0:
                    continue
                draws = {"speedFactor": self.speed_factor(mean, dev)}
            sim.set_driver(vid, **draws)

    def speed_factor(self, mean: float, dev: float) -> float:
        """A draw of N(mean, dev) inside ``SPEED_FACTOR_BOUNDS`` (redrawn outside, as SUMO)."""
        lo, hi = SPEED_FACTOR_BOUNDS
        for _ in range(100):
            x = float(self.rng.normal(mean, dev))
            if lo <= x <= hi:
                return x
        return float(np.clip(mean, lo, hi))

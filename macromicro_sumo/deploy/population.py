"""Who is driven in a deployment, and what a driver counts: the action function's type,
the population a section deploys to (``population_scenario``), the share drawn per vehicle
by a hash, a run's counts (``DriveStats``) and the vType a switch gives (``SwitchedType``).
Shared by the drivers (``deploy.drivers``), the runs (``deploy.run``) and the stage
(``deploy.stage``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from macromicro_sumo.data.section import hidden_per_snapshot, vehicle_level

# Obs (V, D) -> acceleration (V,) [m/s^2]: one batched call for every driven vehicle.
ActionBatch = Callable[[np.ndarray], np.ndarray]


def whole_fleet(sc: Any) -> bool:
    """Whether a section's deployment drives every vehicle: with ``instrumented.hidden =
    "snapshot"`` every vehicle is recorded and each snapshot hides K random ones, so nobody
    is instrumented for good and the population is the whole fleet (as the ring deploys
    it); otherwise the instrumented vehicles keep their own models."""
    return hidden_per_snapshot(sc)


def population_scenario(sc: Any) -> Any:
    """``sc`` as a deployment's drivers and runs read it: where ``whole_fleet``, with no
    vehicle instrumented (the drivers leave instrumented vehicles to SUMO,
    ``truth.section.is_instrumented``; the deployment's trajectories mark none observed),
    else ``sc`` itself. ``deploy.share`` and ``deploy.vtype`` still narrow the population.
    Only ``instrumented`` changes: Stage II's settings (``hidden``, the micro pairs) stay."""
    if not whole_fleet(sc):
        return sc
    nobody = dataclasses.replace(sc.instrumented, ids=[], vtype="", penetration=0.0)
    return dataclasses.replace(sc, instrumented=nobody)


def population_label(sc: Any) -> str:
    """The deployed population in words (each deploy manifest records it)."""
    if whole_fleet(sc):
        who = 'every vehicle (instrumented.hidden = "snapshot": nobody is instrumented for good)'
    else:
        who = "every vehicle that is not instrumented"
    dep = sc.deploy
    if getattr(dep, "vtype", ""):
        who += f", of vType {dep.vtype!r}"
    if dep.share < 1.0:
        who += f", a share {dep.share:g} of them drawn per vehicle"
    return who


def in_share(seed: int, run: int, vehicle_id: str, share: float) -> bool:
    """Whether a vehicle is in a driven share: a hash of (seed, run, vehicle), so the same
    vehicles are chosen whatever method drives and however often the run is repeated."""
    if share >= 1.0:
        return True
    return vehicle_level(seed, run, vehicle_id, "deploy") < share


@dataclass
class DriveStats:
    """What a driver counted over one run."""

    vehicle_steps_driven: int = 0
    safety_acted: int = 0
    emergency_brakings: int = 0
    floor_acted: int = 0  # commands the safety layer raised to its floor (``deploy.safety``)

    def count_safety(self, cmd: np.ndarray, lowered: int, raised: int) -> np.ndarray:
        """``cmd``, the safety layer's commands (``deploy.safety.safety_cap``), after
        counting how many it lowered and raised."""
        self.safety_acted += lowered
        self.floor_acted += raised
        return cmd

    def as_dict(self) -> dict[str, int]:
        return {
            "emergency_brakings": self.emergency_brakings,
            "vehicle_steps_driven": self.vehicle_steps_driven,
            "safety_acted": self.safety_acted,
            "floor_acted": self.floor_acted,
        }


# runs.csv's safety columns beyond the ground truth's: SUMO's counts, then ``DriveStats``'.
SAFETY_COLUMNS = ("collisions", "teleports", *DriveStats().as_dict())


@dataclass
class SwitchedType:
    """A vType switch: the vType each demand vType's vehicles get, and their speed factor
    (a number, or None to draw one per vehicle around SUMO's default 1 with sd 0.1)."""

    type_of: dict[str, str]
    speed_factor: float | None
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    def factors(self, n: int) -> np.ndarray:
        if self.speed_factor is not None:
            return np.full(n, self.speed_factor)
        # SUMO's passenger default: normal(1, 0.1) cut at two deviations.
        return np.clip(self.rng.normal(1.0, 0.1, n), 0.8, 1.2)

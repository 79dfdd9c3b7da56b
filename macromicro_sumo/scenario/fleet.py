"""The heterogeneous IDM fleet as a demand source: ``[fleet]``, ``[speed_limits]``, ``[initial]``.

The paper's ring draws, for every run, each vehicle's IDM parameters, a speed limit per
edge and an initial state away from equilibrium. The same three tables make a closed
one-lane section scenario (``[network] kind = "sumo"``) draw its demand the same way,
instead of reading the user's route files (``truth/fleet.py`` samples, ``sumo/fleet.py``
writes the vehicle types, ``truth/section.py`` inserts and records).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fields import Pair, spec


@dataclass(frozen=True, kw_only=True)
class FleetConfig:
    """Heterogeneous IDM drivers: each vehicle draws its own parameters from these ranges."""

    n_vehicles: int = spec(lo=2, hi=10_000, doc="vehicles on the ring N")
    length_m: float = spec(5.0, lo=0.5, hi=30.0, doc="vehicle length [m]")
    accel_mps2: Pair = spec(lo=0.01, hi=10.0, doc="IDM maximum acceleration a range [m/s^2]")
    decel_mps2: Pair = spec(lo=0.01, hi=10.0, doc="IDM comfortable deceleration b range [m/s^2]")
    tau_s: Pair = spec(lo=0.1, hi=10.0, doc="IDM desired time headway T range [s]")
    min_gap_m: Pair = spec(lo=0.0, hi=50.0, doc="IDM jam distance s0 range [m]")
    delta: float = spec(4.0, lo=1.0, hi=10.0, doc="IDM acceleration exponent (same for all)")
    speed_factor: Pair = spec(lo=0.1, hi=3.0, doc="desired speed / local limit range [-]")
    max_speed_mps: Pair = spec((50.0, 50.0), lo=0.1, hi=100.0, doc="vehicle top speed range [m/s]")


@dataclass(frozen=True, kw_only=True)
class SpeedLimitConfig:
    """Random piecewise-constant limits: each edge draws its own limit per run."""

    range_mps: Pair = spec(lo=0.1, hi=100.0, doc="per-edge limit range [m/s]")
    step_mps: float = spec(
        0.5, lo=0.0, hi=10.0, doc="limits are rounded to this step [m/s] (0: none)"
    )


@dataclass(frozen=True, kw_only=True)
class InitialConfig:
    """Initial conditions away from steady state."""

    speed_mps: Pair = spec(lo=0.0, hi=100.0, doc="initial speeds, uniform in this range [m/s]")
    spacing_concentration: float = spec(
        20.0, lo=0.1, hi=1e6, doc="Dirichlet concentration of initial spacings (high: even)"
    )
    min_spacing_m: float = spec(
        20.0, lo=0.0, hi=1e5, doc="smallest initial front-to-front spacing [m]"
    )


@dataclass(frozen=True)
class FleetDemand:
    """The three tables of a fleet demand source, as the samplers take them."""

    fleet: FleetConfig
    speed_limits: SpeedLimitConfig
    initial: InitialConfig

    def top_speed_mps(self) -> float:
        """The fastest any vehicle of the fleet can drive [m/s] (its desired or start speed)."""
        f = self.fleet
        desired = f.speed_factor[1] * self.speed_limits.range_mps[1]
        return max(min(f.max_speed_mps[1], desired), self.initial.speed_mps[1])


FLEET_TABLES = ("fleet", "speed_limits", "initial")


def check_fleet(demand: FleetDemand, length_m: float, road: str, file: str) -> None:
    """The fleet fits on a closed road of ``length_m`` (``road`` names it in messages)."""
    n, f, init = demand.fleet.n_vehicles, demand.fleet, demand.initial
    if n * f.length_m >= length_m:
        raise UserError(
            f"{file}: fleet of {n} x {f.length_m:g} m does not fit on a {length_m:.2f} m {road}"
        )
    if n * init.min_spacing_m >= length_m:
        raise UserError(
            f"{file}: initial.min_spacing_m = {init.min_spacing_m:g} too large for {n} vehicles; "
            f"accepted < {length_m / n:.2f}"
        )
    if init.min_spacing_m < f.length_m:
        raise UserError(
            f"{file}: initial.min_spacing_m = {init.min_spacing_m:g} < vehicle length "
            f"{f.length_m:g}; accepted >= {f.length_m:g}"
        )


def fleet_demand(sc: Any) -> FleetDemand | None:
    """A section scenario's fleet demand source, or None where its demand is the user's
    route files (the three tables are all there or all absent: ``check_fleet_tables``)."""
    if getattr(sc, "fleet", None) is None:
        return None
    return FleetDemand(sc.fleet, sc.speed_limits, sc.initial)


def check_fleet_tables(sc: Any, file: str) -> None:
    """A section scenario has the three fleet tables together or none, and a fleet demand
    replaces the user's route files (their vehicles would drive among the fleet)."""
    have = [t for t in FLEET_TABLES if getattr(sc, t) is not None]
    if have and len(have) != len(FLEET_TABLES):
        lacking = ", ".join(f"[{t}]" for t in FLEET_TABLES if t not in have)
        raise UserError(
            f"{file}: a fleet demand needs [fleet], [speed_limits] and [initial]; missing {lacking}"
        )
    if have and (sc.network.route_files or sc.network.sumocfg):
        raise UserError(
            f"{file}: [fleet] is the demand: network.route_files and network.sumocfg are not "
            "accepted with it; accepted: net_file (and additional_files)"
        )

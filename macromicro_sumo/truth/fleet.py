"""The heterogeneous IDM fleet's random draws per run, for the ring and closed sections alike.

Each run draws per-vehicle IDM parameters, a speed limit per edge and an initial state
away from equilibrium (Dirichlet spacings with a floor, a random rotation, uniform
speeds capped at each driver's desired speed), all from one seeded generator in run order,
so that a deployment re-draws a run's demand identically. ``truth/ring.py`` and
``truth/section.py`` both insert what these functions draw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.road.ring import RingGeometry
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.fleet import FleetDemand

# SUMO rounds a vehicle's speedFactor to 4 decimals; sampling on that grid keeps the
# recorded parameters exactly the ones SUMO drives with.
PARAM_DECIMALS = 4


@dataclass(frozen=True)
class RunSpec:
    """Everything random about one run, drawn before SUMO starts."""

    run: int
    sumo_seed: int
    limits_mps: np.ndarray  # per edge
    params: pd.DataFrame  # one row per vehicle
    arc0_m: np.ndarray
    speed0_mps: np.ndarray


def sample_limits(demand: FleetDemand, n_edges: int, rng: np.random.Generator) -> np.ndarray:
    """One speed limit per edge [m/s], uniform in the range, rounded to its step."""
    lo, hi = demand.speed_limits.range_mps
    v = rng.uniform(lo, hi, n_edges)
    step = demand.speed_limits.step_mps
    if step > 0:
        v = np.clip(np.round(v / step) * step, lo, hi)
    return v


def sample_initial_arcs(
    demand: FleetDemand, length_m: float, rng: np.random.Generator
) -> np.ndarray:
    """Random angular positions: Dirichlet spacings with a floor, random rotation."""
    n = demand.fleet.n_vehicles
    floor = demand.initial.min_spacing_m
    # Spacings = floor + Dirichlet share of the slack: always feasible, no rejection loop.
    share = rng.dirichlet(np.full(n, demand.initial.spacing_concentration))
    spacing = floor + share * (length_m - n * floor)
    arc = rng.uniform(0.0, length_m) + np.concatenate([[0.0], np.cumsum(spacing)[:-1]])
    return np.mod(arc, length_m)


def sample_run(
    demand: FleetDemand, geo: RingGeometry, run: int, rng: np.random.Generator
) -> RunSpec:
    """Run ``run``'s draws, in this order: limits, parameters, arcs, speeds, SUMO's seed.
    ``demand``: anything with the ``fleet``, ``speed_limits`` and ``initial`` tables."""
    f = demand.fleet
    n = f.n_vehicles

    def draw(pair: tuple[float, float]) -> np.ndarray:
        return np.round(rng.uniform(pair[0], pair[1], n), PARAM_DECIMALS)

    limits = sample_limits(demand, len(geo.edge_ids), rng)
    params = pd.DataFrame(
        {
            "run": run,
            "vehicle_id": [f"v{i}" for i in range(n)],
            "accel_mps2": draw(f.accel_mps2),
            "decel_mps2": draw(f.decel_mps2),
            "tau_s": draw(f.tau_s),
            "min_gap_m": draw(f.min_gap_m),
            "delta": f.delta,
            "speed_factor": draw(f.speed_factor),
            "max_speed_mps": draw(f.max_speed_mps),
            "length_m": f.length_m,
        }
    )
    arc0 = sample_initial_arcs(demand, geo.length_m, rng)
    local_limit = limits[geo.edge_index(arc0)]
    desired = np.minimum(
        params["max_speed_mps"].to_numpy(), params["speed_factor"].to_numpy() * local_limit
    )
    lo, hi = demand.initial.speed_mps
    # A driver never starts above their own desired speed (SUMO refuses such a departure).
    speed0 = np.minimum(rng.uniform(lo, hi, n), desired)
    params["initial_arc_m"] = arc0
    params["initial_speed_mps"] = speed0
    return RunSpec(run, int(rng.integers(0, 2**31 - 1)), limits, params, arc0, speed0)


def run_specs(demand: FleetDemand, geo: RingGeometry, n_runs: int, seed: int) -> list[RunSpec]:
    """Every run's random draws, in run order from ``seed`` (a deployment re-draws them
    identically and picks its runs)."""
    rng = np.random.default_rng(seed)
    return [sample_run(demand, geo, r, rng) for r in range(n_runs)]


def limits_frame(specs: list[RunSpec], geo: RingGeometry) -> pd.DataFrame:
    """speed_limits.csv: each run's limit on each edge, with the edge's arc span."""
    return pd.DataFrame(
        [
            {
                "run": s.run,
                "edge_id": e,
                "start_m": geo.offsets_m[i],
                "end_m": geo.offsets_m[i] + geo.lengths_m[i],
                "speed_limit_mps": s.limits_mps[i],
            }
            for s in specs
            for i, e in enumerate(geo.edge_ids)
        ]
    )


def section_ring(section: Section, where: str) -> RingGeometry:
    """The ring a fleet drives on: a closed one-lane section without junction arcs, read as
    the ring's geometry (the same offsets, so the same draws place the same vehicles)."""
    if not section.closed:
        raise UserError(
            f"{where}: a [fleet] demand needs a closed section (it has no entry or exit); "
            "accepted: section.closed = true"
        )
    if (section.n_lanes != 1).any():
        many = section.edge_ids[int(np.argmax(section.n_lanes != 1))]
        raise UserError(
            f"{where}: a [fleet] demand drives one lane; section edge {many!r} has "
            f"{int(section.n_lanes.max())} lanes; accepted: one lane per edge"
        )
    if (section.junction_m > 1e-6).any():
        raise UserError(
            f"{where}: a [fleet] demand needs a section without junction lanes (the ring "
            "network of scripts/build_ring_net.py); accepted: junction lengths 0"
        )
    lanes = tuple(ids[0] for ids in section.edge_lane_ids)
    return RingGeometry(section.edge_ids, lanes, section.offsets_m.copy(), section.lengths_m.copy())

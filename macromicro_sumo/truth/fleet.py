"""The heterogeneous IDM fleet's random draws per run, for the ring and closed sections alike.

Each run draws per-vehicle IDM parameters, a speed limit per edge and an initial state
away from equilibrium (Dirichlet spacings with a floor, a random rotation, uniform
speeds capped at each driver's desired speed), all from one seeded generator in run order,
so that a deployment re-draws a run's demand identically. ``truth/ring.py`` and
``truth/section.py`` both insert what these functions draw.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.fleet import FleetDemand, check_fleet
from macromicro_sumo.sumo.demand import VType
from macromicro_sumo.sumo.fleet import loop_laps, loop_routes_xml, vtypes_xml
from macromicro_sumo.sumo.simulation import Simulation

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


def sample_run(demand: FleetDemand, geo: Section, run: int, rng: np.random.Generator) -> RunSpec:
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


def run_specs(demand: FleetDemand, geo: Section, n_runs: int, seed: int) -> list[RunSpec]:
    """Every run's random draws, in run order from ``seed`` (a deployment re-draws them
    identically and picks its runs)."""
    rng = np.random.default_rng(seed)
    return [sample_run(demand, geo, r, rng) for r in range(n_runs)]


def limits_frame(specs: list[RunSpec], geo: Section) -> pd.DataFrame:
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


def section_ring(section: Section, where: str) -> Section:
    """``section``, checked to be a ring a fleet can drive on: closed, one lane, without
    junction arcs (so the arc of a vehicle is its edge's offset plus its lane position)."""
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
    return section


# --------------------------------------------------------------------------- a section's fleet


def fleet_vtypes(demand: FleetDemand, geo: Section, where: str) -> dict[str, VType]:
    """The fleet's vehicle types as the section stages see them (one per vehicle, named
    as it): length and the smallest jam distance the draws can give; checks the fit."""
    check_fleet(demand, geo.length_m, "section", where)
    f = demand.fleet
    return {f"v{i}": VType(f"v{i}", f.length_m, f.min_gap_m[0], "IDM") for i in range(f.n_vehicles)}


def write_fleet_inputs(
    run_dir: Path, spec: RunSpec, geo: Section, demand: FleetDemand, dt_s: float, span_s: float
) -> tuple[Path, Path]:
    """(vTypes, routes) additional files of one run of a fleet on a closed section, with
    routes long enough for ``span_s`` seconds at the fleet's largest maxSpeed."""
    vtypes, routes = run_dir / "fleet_vtypes.add.xml", run_dir / "fleet_routes.add.xml"
    vtypes.write_text(vtypes_xml(spec.params, dt_s))
    # A deployment's speed commands may take a driven vehicle past its desired speed, up to
    # its vType's maxSpeed: sized for the fleet's desired speeds the routes ran out (an
    # adversarial driver on the paper ring lost vehicles off the section within 60 s).
    top = max(demand.top_speed_mps(), demand.fleet.max_speed_mps[1])
    laps = loop_laps(geo.length_m, top, span_s)
    routes.write_text(loop_routes_xml(geo.edge_ids, laps))
    return vtypes, routes


def insert_fleet(sim: Simulation, spec: RunSpec, geo: Section, route_prefix: str) -> None:
    """Set the run's limits and queue every vehicle at its drawn arc and speed, on the
    route ``<route_prefix><edge>`` of its start edge (inserted by the next step)."""
    ids = list(spec.params["vehicle_id"])
    edges = geo.edge_index(spec.arc0_m)
    pos = np.clip(
        np.mod(spec.arc0_m, geo.length_m) - geo.offsets_m[edges], 0.0, geo.lengths_m[edges]
    )
    sim.set_lane_speed_limits([lanes[0] for lanes in geo.edge_lane_ids], spec.limits_mps)
    routes = [f"{route_prefix}{geo.edge_ids[e]}" for e in edges]
    sim.add_vehicles(ids, routes, ids, pos.tolist(), spec.speed0_mps)


def insertion_error(
    spec: RunSpec, geo: Section, arc_m: np.ndarray, speed_mps: np.ndarray
) -> tuple[float, float]:
    """(largest arc error [m], largest speed error [m/s]) of the inserted vehicles against
    their draws; ``arc_m``/``speed_mps`` in the order of ``spec.params``."""
    half = geo.length_m / 2
    err = np.abs(np.mod(arc_m - spec.arc0_m + half, geo.length_m) - half)
    return float(err.max()), float(np.abs(speed_mps - spec.speed0_mps).max())


def check_fleet_inserted(sim: Simulation, spec: RunSpec, geo: Section) -> None:
    """After the insertion step: every vehicle is on the road where and as fast as drawn
    (SUMO would otherwise silently delay or move a departure)."""
    ids = list(spec.params["vehicle_id"])
    st = sim.vehicle_states()
    missing = [v for v in ids if v not in st.index]
    if sim.pending_vehicles() or missing:
        raise UserError(
            f"run {spec.run}: SUMO did not insert every vehicle (missing: {missing[:5]})"
        )
    lane = {lanes[0]: i for i, lanes in enumerate(geo.edge_lane_ids)}
    rows = [st.index[v] for v in ids]
    on = [lane.get(st.lanes[r], -1) for r in rows]
    if min(on) < 0:
        raise UserError(f"run {spec.run}: an inserted vehicle is off the section")
    arc = geo.offsets_m[np.array(on)] + st.pos_m[rows]
    arc_err, speed_err = insertion_error(spec, geo, arc, st.speed_mps[rows])
    if arc_err > 0.01 or speed_err > 0.01:
        raise UserError(
            f"run {spec.run}: inserted vehicles are off their sampled state by {arc_err:.3f} m, "
            f"{speed_err:.3f} m/s"
        )

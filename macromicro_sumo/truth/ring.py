"""Ground truth: heterogeneous IDM fleets on the SUMO ring, recorded with loop detectors.

For each run: sample per-vehicle IDM parameters, piecewise speed limits and an initial
state away from equilibrium (``truth/fleet.py``); insert the fleet through the SUMO boundary; step and record
every vehicle; then derive leaders, spacings and gaps from arc positions (not from SUMO's
getLeader). Outputs (all in the output folder, written atomically):
trajectories.csv, vehicles.csv, speed_limits.csv, runs.csv, detectors.csv,
detector_passages.csv, macro.csv, manifest.json and SUMO's own XML under sumo/.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.data import macro
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import (
    check_memory,
    prepare_out_dir,
    staging_dir,
    write_csv,
    write_manifest,
)
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.physics import forward_accel, ring_leaders
from macromicro_sumo.road.ring import RingGeometry, read_ring
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.sumo.demand import check_ring_routes
from macromicro_sumo.sumo.fleet import vtypes_xml
from macromicro_sumo.sumo.simulation import Driver, Simulation, SumoOptions
from macromicro_sumo.truth import fleet
from macromicro_sumo.truth import ring_detectors as detectors
from macromicro_sumo.truth.fleet import RunSpec

# Peak memory of `simulate` per trajectory row (run x step x vehicle): 245 B measured on
# 720,000 rows (the per-run frames, their concatenation, macro statistics, CSV writing).
BYTES_PER_ROW = 256


@dataclass
class RunRecord:
    arc_m: np.ndarray  # (T+1, N), wrapped to [0, L)
    speed_mps: np.ndarray  # (T+1, N)
    collisions: int
    teleports: int
    wall_s: float
    time0_s: float  # SUMO time of the first recorded state (after the insertion step)


def record_run(
    sim: Simulation,
    spec: RunSpec,
    geo: RingGeometry,
    n_steps: int,
    driver: Driver | None = None,
) -> RunRecord:
    """Insert the fleet, verify the insertion, then step and record every vehicle.
    ``driver`` (a deployment) acts before every step after the insertion; None: SUMO
    drives every vehicle with its own IDM."""
    ids = list(spec.params["vehicle_id"])
    fleet.insert_fleet(sim, spec, geo, "r_")  # the routes r_<edge> of network.routes_file
    t0 = time.perf_counter()
    sim.step()
    if sim.pending_vehicles() or len(sim.vehicle_ids()) != len(ids):
        raise UserError(
            f"run {spec.run}: SUMO did not insert every vehicle (pending: {sim.pending_vehicles()})"
        )
    sim.subscribe(ids)
    edge_index = {e: i for i, e in enumerate(geo.edge_ids)}
    n = len(ids)
    arc = np.empty((n_steps + 1, n))
    speed = np.empty((n_steps + 1, n))
    collisions = teleports = 0
    e, p, v = sim.read_states(ids, edge_index)
    arc[0], speed[0] = geo.offsets_m[e] + p, v
    time0 = sim.time_s()
    for t in range(1, n_steps + 1):
        if driver is not None:
            driver.before_step(sim)
        sim.step()
        e, p, v = sim.read_states(ids, edge_index)
        arc[t] = geo.offsets_m[e] + p
        speed[t] = v
        collisions += sim.collisions()
        teleports += sim.teleports()
    wall = time.perf_counter() - t0
    arc_err, speed_err = fleet.insertion_error(spec, geo, arc[0], speed[0])
    if arc_err > 0.01 or speed_err > 0.01:
        raise UserError(
            f"run {spec.run}: inserted vehicles are off their sampled state by {arc_err:.3f} m"
        )
    return RunRecord(np.mod(arc, geo.length_m), speed, collisions, teleports, wall, time0)


def trajectory_frame(spec: RunSpec, rec: RunRecord, geo: RingGeometry, dt_s: float) -> pd.DataFrame:
    """Per run, step and vehicle: state, action, leader, spacing and gap (from arc positions)."""
    arc, speed = rec.arc_m[:-1], rec.speed_mps[:-1]
    steps, n = arc.shape
    leader, spacing = ring_leaders(arc, geo.length_m)
    lengths = spec.params["length_m"].to_numpy()
    ids = np.array(spec.params["vehicle_id"])
    return pd.DataFrame(
        {
            "run": spec.run,
            "time_s": np.repeat(np.round(rec.time0_s + np.arange(steps) * dt_s, 6), n),
            "vehicle_id": np.tile(ids, steps),
            "arc_pos_m": arc.ravel(),
            "theta_rad": (2 * np.pi * arc / geo.length_m).ravel(),
            "speed_mps": speed.ravel(),
            "accel_mps2": forward_accel(rec.speed_mps, dt_s).ravel(),
            "leader_id": ids[leader].ravel(),
            "spacing_m": spacing.ravel(),
            "gap_m": (spacing - lengths[leader]).ravel(),
            "leader_speed_mps": np.take_along_axis(speed, leader, axis=1).ravel(),
            "speed_limit_mps": spec.limits_mps[geo.edge_index(arc)].ravel(),
        }
    )


def check_ring(sc: Scenario) -> tuple[RingGeometry, Path, Path]:
    """(geometry, net file, routes file) of the scenario's ring, checked against it."""
    net_file = sc.resolve(sc.network.net_file)
    routes_file = sc.resolve(sc.network.routes_file)
    geo = read_ring(net_file)
    if abs(geo.length_m - sc.network.length_m) > 1e-3:
        raise UserError(
            f"{net_file}: ring length {geo.length_m:.4f} m does not match network.radius_m = "
            f"{sc.network.radius_m:g} (2 pi R = {sc.network.length_m:.4f} m)"
        )
    check_ring_routes(routes_file, geo.edge_ids, net_file)
    return geo, net_file, routes_file


def run_specs(sc: Scenario, geo: RingGeometry) -> list[RunSpec]:
    """Every run's random draws, in run order from ``sc.seed`` (a deployment re-draws
    them identically and picks its runs)."""
    return fleet.run_specs(sc.fleet_demand, geo, sc.simulation.n_runs, sc.seed)


def run_ring(
    sc: Scenario,
    geo: RingGeometry,
    files: tuple[Path, Path],
    stage: Path,
    specs: Sequence[RunSpec],
    progress: bool = True,
    driver_for: Callable[[RunSpec], Driver | None] | None = None,
    extra_additional: tuple[Path, ...] = (),
    desc: str = "simulate",
) -> tuple[list[pd.DataFrame], list[dict], list[RunRecord]]:
    """Step the runs of ``specs`` (SUMO's files under ``stage/sumo``); returns their
    trajectory frames, runs.csv rows and records. ``files``: (net, routes);
    ``driver_for(spec)``: who drives besides SUMO (a deployment), with the vTypes it
    switches to in ``extra_additional``."""
    net_file, routes_file = files
    dt = sc.simulation.step_length_s
    n_steps = int(round(sc.simulation.duration_s / dt))
    traj, runs, records = [], [], []
    sim: Simulation | None = None
    try:
        for spec in tqdm(specs, desc=desc, unit="run", disable=not progress):
            run_dir = stage / "sumo" / f"run_{spec.run:03d}"
            run_dir.mkdir(parents=True)
            (run_dir / "vtypes.add.xml").write_text(vtypes_xml(spec.params, dt))
            (run_dir / "detectors.add.xml").write_text(detectors.detectors_xml(geo, sc.detectors))
            adds = (routes_file, run_dir / "vtypes.add.xml", run_dir / "detectors.add.xml")
            opts = SumoOptions(
                net_file,
                (*adds, *extra_additional),
                dt,
                spec.sumo_seed,
                error_log=run_dir / "sumo.log",
            )
            sim = Simulation(opts)  # after the first run: reloads the one libsumo simulation
            driver = driver_for(spec) if driver_for is not None else None
            rec = record_run(sim, spec, geo, n_steps, driver)
            df = trajectory_frame(spec, rec, geo, dt)
            traj.append(df)
            records.append(rec)
            runs.append(
                {
                    "run": spec.run,
                    "sumo_seed": spec.sumo_seed,
                    "collisions": rec.collisions,
                    "teleports": rec.teleports,
                    "min_gap_m": float(df["gap_m"].min()),
                    "mean_speed_mps": float(df["speed_mps"].mean()),
                    "spacing_std_m": float(df["spacing_m"].std()),
                    "sim_wall_s": rec.wall_s,
                }
            )
    finally:
        if sim is not None:
            sim.close()  # SUMO writes a run's detector files when the next load or close ends it
    return traj, runs, records


def ring_detector_tables(
    sc: Scenario, geo: RingGeometry, stage: Path, specs: Sequence[RunSpec], traj: pd.DataFrame
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """(detectors.csv, detector_passages.csv, macro.csv) of the runs of ``specs``."""
    det, passages = [], []
    for spec in specs:
        d, p = detectors.read_run(stage / "sumo" / f"run_{spec.run:03d}", spec.run, geo)
        det.append(d)
        passages.append(p)
    det_df = pd.concat(det, ignore_index=True)
    pas_df = pd.concat(passages, ignore_index=True)
    macro_df = macro.macro_table(
        traj, det_df, pas_df, geo.length_m, sc.detectors.interval_s, sc.simulation.duration_s
    )
    return det_df, pas_df, macro_df


def simulate(sc: Scenario, out: Path | str, command: str = "", progress: bool = True) -> Path:
    """Run every ground-truth run of ``sc`` and write the outputs into ``out``."""
    runs, n = sc.simulation.n_runs, sc.fleet.n_vehicles
    steps = int(round(sc.simulation.duration_s / sc.simulation.step_length_s))
    check_memory(
        runs * steps * n * BYTES_PER_ROW,
        f"{sc.source}: simulation.n_runs x duration_s / step_length_s x fleet.n_vehicles = "
        f"{runs} x {steps} x {n} = {runs * steps * n:,} trajectory rows",
        "lower one of them (or split the runs over several scenarios with `macromicro batch`)",
    )
    out = prepare_out_dir(out)
    geo, net_file, routes_file = check_ring(sc)
    specs = run_specs(sc, geo)
    t_start = time.perf_counter()
    with staging_dir(out) as stage:
        traj, runs, _ = run_ring(sc, geo, (net_file, routes_file), stage, specs, progress)
        traj_df = pd.concat(traj, ignore_index=True)
        det_df, pas_df, macro_df = ring_detector_tables(sc, geo, stage, specs, traj_df)
        limits_df = fleet.limits_frame(specs, geo)
        runs_df = pd.DataFrame(runs)
        write_csv(traj_df, stage / "trajectories.csv")
        write_csv(pd.concat([s.params for s in specs], ignore_index=True), stage / "vehicles.csv")
        write_csv(limits_df, stage / "speed_limits.csv")
        write_csv(runs_df.drop(columns="sim_wall_s"), stage / "runs.csv")
        write_csv(det_df, stage / "detectors.csv")
        write_csv(pas_df, stage / "detector_passages.csv")
        write_csv(macro_df, stage / "macro.csv")
        manifest = build_manifest(sc, command, stage="simulate")
        manifest["ring_length_m"] = geo.length_m
        manifest["collisions"] = int(runs_df["collisions"].sum())
        manifest["teleports"] = int(runs_df["teleports"].sum())
        manifest["timings_s"] = {"simulate": round(time.perf_counter() - t_start, 3)}
        write_manifest(manifest, stage)
    return out

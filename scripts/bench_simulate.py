"""Benchmark: the ground-truth recording loop against a bare libsumo loop, same run.

Both loops drive the same SUMO set-up (network, vTypes, detectors, limits, inserted
fleet) for the same number of steps, and read the same things from SUMO each step
(subscription results, collision and teleport counts). The recording loop is the
package's ``ground_truth.record_run``; the bare loop reads and throws away. The ratio is
the cost of recording; the target is at most 2x.

    python scripts/bench_simulate.py                       # paper ring, N = 5
    python scripts/bench_simulate.py --n-vehicles 22       # denser ring
    python scripts/bench_simulate.py --end-to-end          # plus the whole simulate stage
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

import libsumo  # benchmarks may talk to SUMO directly; the package goes through sumo.py
import numpy as np
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.truth.ring import record_run, simulate

from macromicro_sumo.road.ring import RingGeometry, read_ring
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.fleet import vtypes_xml
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth import ring_detectors as detectors
from macromicro_sumo.truth.fleet import RunSpec, sample_run

ROOT = Path(__file__).resolve().parents[1]
TARGET_RATIO = 2.0


def insert_fleet(sim: Simulation, spec: RunSpec, geo: RingGeometry) -> list[str]:
    """The same insertion as record_run, without recording."""
    ids = list(spec.params["vehicle_id"])
    edges, pos = zip(*(geo.to_edge(a) for a in spec.arc0_m), strict=True)
    sim.set_lane_speed_limits(geo.lane_ids, spec.limits_mps)
    sim.add_vehicles(ids, [f"r_{geo.edge_ids[e]}" for e in edges], ids, pos, spec.speed0_mps)
    sim.step()
    assert len(sim.vehicle_ids()) == len(ids), "fleet not inserted"
    sim.subscribe(ids)
    return ids


def bare_loop(sim: Simulation, spec: RunSpec, geo: RingGeometry, n_steps: int) -> float:
    """Seconds for insertion + n_steps of stepping and reading, nothing kept."""
    t0 = time.perf_counter()
    insert_fleet(sim, spec, geo)
    libsumo.vehicle.getAllSubscriptionResults()
    for _ in range(n_steps):
        libsumo.simulationStep()
        libsumo.vehicle.getAllSubscriptionResults()
        libsumo.simulation.getCollidingVehiclesNumber()
        libsumo.simulation.getStartingTeleportNumber()
    return time.perf_counter() - t0


def step_only_loop(sim: Simulation, spec: RunSpec, geo: RingGeometry, n_steps: int) -> float:
    t0 = time.perf_counter()
    insert_fleet(sim, spec, geo)
    for _ in range(n_steps):
        libsumo.simulationStep()
    return time.perf_counter() - t0


def recording_loop(sim: Simulation, spec: RunSpec, geo: RingGeometry, n_steps: int) -> float:
    t0 = time.perf_counter()
    rec = record_run(sim, spec, geo, n_steps)
    wall = time.perf_counter() - t0
    assert rec.arc_m.shape == (n_steps + 1, len(spec.arc0_m))
    return wall


def scenario_for(args: argparse.Namespace) -> Scenario:
    overrides: dict[str, object] = {"simulation.duration_s": args.duration}
    if args.n_vehicles is not None:
        # A denser ring: drop the paper's spacing bounds, keep initial spacings feasible.
        overrides |= {
            "fleet.n_vehicles": args.n_vehicles,
            "bounds.spacing_m": [0.0, 1e5],
            "initial.min_spacing_m": 10.0,
            "initial.speed_mps": [4.0, 6.0],
        }
    return load_scenario(args.scenario, overrides)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", type=Path, default=ROOT / "scenarios" / "ring_paper.toml")
    ap.add_argument("--duration", type=float, default=3600.0, help="simulated seconds per loop")
    ap.add_argument("--repeats", type=int, default=5, help="interleaved repeats (median shown)")
    ap.add_argument("--n-vehicles", type=int, default=None, help="override the fleet size")
    ap.add_argument("--end-to-end", action="store_true", help="also time simulate() whole")
    ap.add_argument("--check", action="store_true", help="exit 1 when the ratio misses 2x")
    args = ap.parse_args(argv)

    sc = scenario_for(args)
    net = sc.resolve(sc.network.net_file)
    geo = read_ring(net)
    dt = sc.simulation.step_length_s
    n_steps = round(sc.simulation.duration_s / dt)
    spec = sample_run(sc, geo, 0, np.random.default_rng(sc.seed))
    n = len(spec.arc0_m)

    walls: dict[str, list[float]] = {"recording": [], "bare": [], "step_only": []}
    loops = {"recording": recording_loop, "bare": bare_loop, "step_only": step_only_loop}
    with tempfile.TemporaryDirectory() as tmp:
        sim: Simulation | None = None
        try:
            for r in range(args.repeats):
                for name, loop in loops.items():
                    run_dir = Path(tmp) / f"{name}_{r}"
                    run_dir.mkdir()
                    (run_dir / "vtypes.add.xml").write_text(vtypes_xml(spec.params, dt))
                    (run_dir / "det.add.xml").write_text(detectors.detectors_xml(geo, sc.detectors))
                    opts = SumoOptions(
                        net,
                        (
                            sc.resolve(sc.network.routes_file),
                            run_dir / "vtypes.add.xml",
                            run_dir / "det.add.xml",
                        ),
                        dt,
                        spec.sumo_seed,
                        error_log=run_dir / "sumo.log",
                    )
                    sim = Simulation(
                        opts
                    )  # after the first run: reloads the one libsumo simulation
                    walls[name].append(loop(sim, spec, geo, n_steps))
        finally:
            if sim is not None:
                sim.close()

        rate = {k: n * n_steps / statistics.median(v) for k, v in walls.items()}
        ratio = rate["bare"] / rate["recording"]
        print(
            f"scenario {sc.name}: N = {n} vehicles, dt = {dt:g} s, {n_steps} steps per loop, "
            f"{args.repeats} interleaved repeats (median), libsumo {version('libsumo')}"
        )
        print(
            f"  recording (ground_truth.record_run) : {rate['recording']:>12,.0f} vehicle-steps/s"
        )
        print(f"  bare libsumo loop, same reads       : {rate['bare']:>12,.0f} vehicle-steps/s")
        print(
            f"  bare libsumo loop, step only        : {rate['step_only']:>12,.0f} vehicle-steps/s"
        )
        verdict = "OK" if ratio <= TARGET_RATIO else "MISSED"
        print(
            f"  recording costs {ratio:.2f}x the bare loop (target <= {TARGET_RATIO:g}x): {verdict}"
        )

        if args.end_to_end:
            full = load_scenario(args.scenario)
            t0 = time.perf_counter()
            simulate(full, Path(tmp) / "e2e", progress=False)
            wall = time.perf_counter() - t0
            steps = full.simulation.n_runs * round(
                full.simulation.duration_s / full.simulation.step_length_s
            )
            print(
                f"  simulate() end to end ({full.simulation.n_runs} runs, CSVs, detectors, macro): "
                f"{full.fleet.n_vehicles * steps / wall:,.0f} vehicle-steps/s ({wall:.2f} s)"
            )
    return 1 if args.check and ratio > TARGET_RATIO else 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark SectionCore on SUMO's Bremen motorway section against a bare libsumo loop.

Prints env steps/s (resets every H steps included, random actions) of ``SectionCore`` and
of a bare libsumo loop making the same SUMO calls (at each reset: remove, add every
vehicle, one step, speed mode; per step: setSpeed for every vehicle, simulationStep, the
lane, position and speed of every vehicle by getters), and the ratio. Episodes are the
recorded scenes of a short ground truth (true hidden vehicles as the generated ones).
``bench_core`` and ``run_core`` time any SectionCore (``bench_env.py`` and
``bench_generator.py`` use them).

    python scripts/bench_section_env.py [--steps 5000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import libsumo
import numpy as np

from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[1]


def true_completion(s):
    order = np.argsort(np.where(s.valid, np.where(s.observed, 0, 1), 2), axis=1, kind="stable")
    take = lambda a: np.take_along_axis(a, order, 1)  # noqa: E731
    return take(s.lane), take(s.arc_m), take(s.speed_mps), take(s.valid), take(s.hidden)


def run_core(core: SectionCore, steps: int, rng: np.random.Generator) -> int:
    """Random episodes of H steps of random actions (a truncated one ends early) until
    ``steps`` env steps; returns the steps made."""
    done = 0
    while done < steps:
        core.reset(int(rng.integers(len(core.bank))))
        k = int(core.hidden.sum())
        for _ in range(core.bank.horizon):
            done += 1
            if core.step(rng.uniform(-1.0, 1.0, k)).truncated:
                break
    return done


def bench_core(
    core: SectionCore,
    steps: int,
    rng: np.random.Generator,
    clock: Callable[[], float] = time.perf_counter,
) -> float:
    """Env steps per second of ``clock`` (wall by default; ``time.process_time``: CPU
    seconds of this process, SUMO included through libsumo) of ``run_core``."""
    t0 = clock()
    done = run_core(core, steps, rng)
    return done / (clock() - t0)


def bench_bare(core: SectionCore, steps: int, rng: np.random.Generator) -> float:
    """The same libsumo calls as SectionCore, with no Python-side modelling."""
    bank, sec = core.bank, core.section
    t0 = time.perf_counter()
    done = resets = 0
    while done < steps:
        ep = int(rng.integers(len(bank)))
        for vid in libsumo.vehicle.getIDList():
            libsumo.vehicle.remove(vid)
        resets += 1
        slots = np.flatnonzero(bank.valid[ep])
        ids = [f"b{resets}.{i}" for i in slots]
        for vid, i in zip(ids, slots, strict=True):
            e, lane, pos = core.section.to_lane(int(bank.lane0[ep, i]), float(bank.arc0_m[ep, i]))
            libsumo.vehicle.add(
                vid,
                f"mm_r{e}",
                typeID=core._vtype[float(np.round(bank.length_m[ep, i], 2))],
                depart="now",
                departLane=str(lane),
                departPos=repr(pos),
                # No faster than the lane allows (a fleet's limits are per run, the net's
                # may be lower).
                departSpeed=repr(
                    min(
                        float(bank.speed0_mps[ep, i]),
                        44.0,
                        libsumo.lane.getMaxSpeed(f"{sec.edge_ids[e]}_{lane}"),
                    )
                ),
            )
        libsumo.simulationStep()
        for vid in ids:
            libsumo.vehicle.setSpeedMode(vid, 0)
        speed = dict(zip(ids, bank.speed0_mps[ep, slots].tolist(), strict=True))
        for _ in range(bank.horizon):
            for vid in ids:
                libsumo.vehicle.setSpeed(vid, speed[vid])
            libsumo.simulationStep()
            gone = set(libsumo.simulation.getArrivedIDList())  # past the open end
            ids = [vid for vid in ids if vid not in gone]
            for vid in ids:  # SectionCore's read: lane, position, speed by getters
                libsumo.vehicle.getLaneID(vid)
                libsumo.vehicle.getLanePosition(vid)
                libsumo.vehicle.getSpeed(vid)
            done += 1
    return done / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        src = ROOT / "scenarios" / "highway_bremen.toml"
        text = src.read_text().replace('"../sumo_nets', f'"{ROOT}/sumo_nets')
        text = text.replace("duration_s = 600.0", "duration_s = 240.0")
        path = Path(tmp) / "highway.toml"
        path.write_text(text.replace("n_runs = 4", "n_runs = 2"))
        sc = load_scenario(path)
        truth = load_section_truth(simulate_section(sc, Path(tmp) / "gt", progress=False), sc)
        snaps = section_snapshots(truth, sc, truth.runs)
        bank = build_section_bank(sc, truth, snaps, true_completion, sc.policy.horizon, sc.seed)
        net = ROOT / "sumo_nets" / "highway_bremen" / "highway.net.xml"
        n_veh = bank.valid.sum(axis=1)
        print(
            f"Bremen motorway section: {truth.section.length_m:.0f} m, {len(bank)} episodes, "
            f"{n_veh.mean():.0f} vehicles per scene ({n_veh.min()}-{n_veh.max()}), "
            f"H = {bank.horizon}, step {sc.simulation.step_length_s} s"
        )
        core = SectionCore(sc, truth.section, bank, net, seed=0)
        try:
            for r in range(args.repeats):
                env_s = bench_core(core, args.steps, np.random.default_rng([sc.seed, r]))
                bare_s = bench_bare(core, args.steps, np.random.default_rng([sc.seed, r]))
                print(
                    f"  repeat {r}: SectionCore {env_s:8,.0f} steps/s | bare libsumo, same calls "
                    f"{bare_s:8,.0f} steps/s | ratio {env_s / bare_s:.2f}"
                )
        finally:
            core.close()
        # Per-step cost against the number of vehicles: the same scenes, thinned to the
        # first n slots (observed and hidden alike).
        print("  per-step cost vs vehicles (same scenes, thinned):")
        for n in (10, 20, 40, int(n_veh.max())):
            keep = np.arange(bank.valid.shape[1]) < n
            thin = dataclasses.replace(bank, valid=bank.valid & keep, hidden=bank.hidden & keep)
            v = thin.valid.sum(axis=1).mean()
            core = SectionCore(sc, truth.section, thin, net, seed=0)
            try:
                rate = bench_core(core, args.steps // 2, np.random.default_rng([sc.seed, n]))
            finally:
                core.close()
            us = 1e6 / rate
            print(
                f"    {v:5.1f} vehicles: {rate:8,.0f} steps/s, {us:7.0f} us/step, "
                f"{us / v:6.1f} us per vehicle-step"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What the ground truth's recorder (``truth.section.record_run``) costs a step, call by
call, on one Bremen run (the example's demand, run 0, as ``scripts/bench_deploy.py`` runs
it) with SUMO driving: thread CPU time of each of its per-step calls between SUMO's steps
(one timer pair around each call a step: the syscalls' own cost is in the figures, ~0.3 us
a call), and each vehicle's instrumented draw (``truth.section.is_instrumented``) taken
between SUMO's steps, as record_run did before stop 45, against once after the run, as
it does now (the same draws, checked). Medians of ``--repeats`` runs, us a step. The
machine's load moves the figures (the load average is printed): compare within a run.

    PYTHONPATH=$PWD .venv/bin/python scripts/bench_recorder.py [--repeats 3] [--steps N]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import is_instrumented, load_section
from macromicro_sumo.truth.section_rows import SectionRows

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("bench_deploy", ROOT / "scripts/bench_deploy.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)

PARTS = ("departed", "vehicle types", "collisions", "teleports", "state read", "rows.add")
DRAWS = ("draws between steps", "draws after the run")


def one_run(sc, steps: int | None = None) -> tuple[dict[str, float], int, int]:
    """(thread CPU [s] by part, steps, draws) of one Bremen run 0 with SUMO driving."""
    inputs, section, _ = load_section(sc)
    opts = SumoOptions(
        inputs.net_file,
        inputs.additional_files,
        sc.simulation.step_length_s,
        sc.seed,
        route_files=inputs.route_files,
        user_demand=True,
    )
    dt = sc.simulation.step_length_s
    n = steps or int(round((sc.simulation.warmup_s + sc.simulation.duration_s) / dt))
    s: dict[str, float] = defaultdict(float)
    clock = time.thread_time
    types: dict[str, str] = {}
    between: dict[str, bool] = {}
    rows = SectionRows(section)
    sim = Simulation(opts)
    try:
        for step in range(n):
            sim.step()
            t0 = clock()
            new = sim.departed()
            t1 = clock()
            for vid in new:
                types[vid] = sim.vehicle_type(vid)
            t2 = clock()
            sim.collisions()
            t3 = clock()
            sim.teleports()
            t4 = clock()
            st = sim.vehicle_states()
            t5 = clock()
            rows.add(round((step + 1) * dt, 6), st)
            t6 = clock()
            for vid in new:
                between[vid] = is_instrumented(sc, vid, types[vid], 0)
            t7 = clock()
            ts = (t0, t1, t2, t3, t4, t5, t6)
            for i, part in enumerate(PARTS):
                s[part] += ts[i + 1] - ts[i]
            s[DRAWS[0]] += t7 - t6
    finally:
        sim.close()
    t0 = clock()
    after = {vid: is_instrumented(sc, vid, vt, 0) for vid, vt in types.items()}
    s[DRAWS[1]] = clock() - t0
    if after != between:
        raise AssertionError("the draws after the run differ from those between the steps")
    return dict(s), n, len(types)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--steps", type=int, default=None, help="steps a run (default: all)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        sc = bench.bremen_scenario(Path(tmp))
        got = [one_run(sc, args.steps) for _ in range(args.repeats)]
    steps, draws = got[0][1], got[0][2]
    print(
        f"recorder's calls, thread CPU us a step (Bremen run 0, {steps} steps, {draws} "
        f"vehicles; median of {args.repeats} runs; load {os.getloadavg()[0]:.1f}):"
    )
    for part in (*PARTS, *DRAWS):
        print(f"  {part:22s} {1e6 * statistics.median(g[0][part] for g in got) / steps:7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Instructions of one Bremen deployment run (``scripts/bench_deploy.py``'s run 0: the
Bremen example's demand, the whole run, the policy in the loop or the oracle), counted by
valgrind's callgrind with only the run itself instrumented: not Python's start, the imports,
the scenario or the policy's load. A bit-identical speed change does the same run with
fewer instructions, and the count is the one measure of it that the shared machine's load
does not move: bench_deploy's ratio moves by +-0.03x with the load (a change of 10 us a
policy step moves it ~0.003x), a count of the same run by a few parts in 10^5 (stop 46).

    PYTHONHASHSEED=0 OPENBLAS_NUM_THREADS=1 valgrind --tool=callgrind --instr-atstart=no \\
        --callgrind-out-file=OUT .venv/bin/python scripts/bench_instructions.py \\
        [--method policy|oracle] [--checkpoint runs/highway_bremen/policy/policy.pt] \\
        [--actor-dtype float64|float32] [--duration-s 600]

valgrind prints the count at exit ("I refs"; ``callgrind_annotate OUT`` splits it by
function). Under callgrind the script switches instrumentation on for the run and off after
it (``callgrind_control``); started without valgrind it runs the same run, says so and
counts nothing. About 10 min a policy run under callgrind at load 15 (1.3 s without).
PYTHONHASHSEED=0 keeps Python's set and dict orders, and so the run's work, the same from
one process to the next.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import os
import subprocess
import tempfile
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent


def bench_module():
    """``scripts/bench_deploy.py`` as a module (its Bremen scenario, policy and run)."""
    spec = importlib.util.spec_from_file_location("bench_deploy", HERE / "bench_deploy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def under_valgrind() -> bool:
    """Whether this process runs under valgrind (its preloaded core library)."""
    return "vgpreload" in os.environ.get("LD_PRELOAD", "")


def instrument(on: bool) -> None:
    """callgrind's instrumentation of this process switched on or off (no-op outside)."""
    if under_valgrind():
        how = "on" if on else "off"
        subprocess.run(
            ["callgrind_control", "-i", how, str(os.getpid())], check=True, capture_output=True
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--method", choices=("policy", "oracle"), default="policy")
    ap.add_argument(
        "--checkpoint",
        type=Path,
        default=HERE.parent / "runs" / "highway_bremen" / "policy" / "policy.pt",
        help="the Bremen policy (as bench_deploy.py's; none: an untrained residual)",
    )
    ap.add_argument("--actor-dtype", choices=("float64", "float32"), help="default: the scenario's")
    ap.add_argument(
        "--duration-s",
        type=float,
        help="a shorter run: this many seconds after no warm-up (default: the scenario's)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    bench = bench_module()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        sc = bench.bremen_scenario(tmp)
        if args.duration_s is not None:
            short = dataclasses.replace(sc.simulation, warmup_s=0.0, duration_s=args.duration_s)
            sc = dataclasses.replace(sc, simulation=short)
        agent, which = bench.agent_for(sc, args.checkpoint)
        act = bench.policy_batch(agent, args.actor_dtype or sc.deploy.actor_dtype)
        instrument(True)
        try:
            _, vs, stats = bench.bremen_run(sc, tmp, args.method, act, run=0)
        finally:
            instrument(False)
    steps = round((sc.simulation.warmup_s + sc.simulation.duration_s) / sc.simulation.step_length_s)
    where = "counted by callgrind" if under_valgrind() else "not counted: not under valgrind"
    print(
        f"{args.method} run 0 of the Bremen demand, {steps} steps, {vs:,} vehicle-steps, "
        f"{stats.get('vehicle_steps_driven', 0):,} driven; policy: {which}; {where}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

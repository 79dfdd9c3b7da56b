"""Wall time of a batch sweep with 1 and 2 local workers (and optionally Ray), in one run.

    .venv/bin/python scripts/bench_batch.py                      # scenarios/ring_sweep.toml
    .venv/bin/python scripts/bench_batch.py --workers 1 2 --ray --repeat 3 --min-speedup 1.8

Each configuration runs the whole sweep (``simulate`` stage) into a fresh folder; the
per-variant CSVs of every configuration must be byte-identical. With ``--repeat N`` the
configurations run interleaved N times and the best wall time of each counts (other work
on a shared machine only ever slows a run down). Prints one line per run, then the best
times and speed-ups over the first configuration; exits 1 when a variant failed, the bytes
differ, or the speed-up of the last local configuration is below ``--min-speedup``.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

from macromicro_sumo.batch.runner import run_batch
from macromicro_sumo.batch.sweep import expand

ROOT = Path(__file__).resolve().parents[1]


def variant_csvs(out: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(out)): p.read_bytes() for p in sorted((out / "variants").rglob("*.csv"))
    }


def _children_cpu_s() -> float:
    """CPU seconds of finished child processes (the local workers, once their pool closed).

    With N workers a share near 100% of N CPUs means the workers got the CPUs; a lower
    share means other work on the machine took them, and the speed-up shows that, not us.
    """
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _self_cpu_s() -> float:
    """CPU seconds of this process (the batch driver)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _machine_busy_s() -> float:
    """CPU seconds the whole machine was busy (Linux /proc/stat; 0 elsewhere)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return 0.0
    user, nice, system, _idle, _iowait, irq, softirq, steal = map(int, fields[:8])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def get_options(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", type=Path, default=ROOT / "scenarios" / "ring_sweep.toml")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="local worker counts")
    ap.add_argument("--ray", action="store_true", help="also run on a local Ray instance")
    ap.add_argument("--repeat", type=int, default=1, help="runs per configuration (best counts)")
    ap.add_argument(
        "--min-speedup", type=float, default=0.0, help="fail below this speed-up (last vs first)"
    )
    return ap.parse_args(argv)


def main(options: argparse.Namespace) -> bool:
    n = len(expand([options.scenario]))
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"sweep: {options.scenario.name}, {n} variants, stage simulate; {cpus} CPUs available")
    configs = [("local", w) for w in options.workers]
    if options.ray:
        configs.append(("ray", max(options.workers)))
    walls: dict[tuple[str, int], float] = {}
    reference: dict[str, bytes] | None = None
    ok = True
    for rep in range(options.repeat):
        for backend, workers in configs:
            with tempfile.TemporaryDirectory(prefix="bench-batch-") as tmp:
                load = os.getloadavg()[0]
                cpu0, busy0, self0 = _children_cpu_s(), _machine_busy_s(), _self_cpu_s()
                t0 = time.perf_counter()
                res = run_batch(
                    [options.scenario], tmp, workers=workers, backend=backend, progress=False
                )
                wall = time.perf_counter() - t0
                cpu = _children_cpu_s() - cpu0  # local workers only: Ray's are not our children
                others = _machine_busy_s() - busy0 - cpu - (_self_cpu_s() - self0)
                csvs = variant_csvs(Path(tmp))
            walls[(backend, workers)] = min(wall, walls.get((backend, workers), wall))
            same = reference is None or csvs == reference
            reference = reference or csvs
            complete = res.counts.get("complete", 0)
            ok &= complete == n and same
            per_variant = res.summary["wall_s"].mean()
            share = f"{cpu / (wall * workers):4.0%}" if backend == "local" else " n/a"
            other = f"{others / wall:4.2f}" if backend == "local" else " n/a"
            print(
                f"run {rep + 1}: {backend:5s} workers={workers}: {wall:6.2f} s  "
                f"workers' CPU share {share}  other processes' CPUs {other}  "
                f"mean variant {per_variant:.2f} s  load before {load:.2f}  "
                f"complete {complete}/{n}  CSVs {'identical' if same else 'DIFFER'}"
            )
    for config in configs:
        print(
            f"best: {config[0]:5s} workers={config[1]}: {walls[config]:6.2f} s  "
            f"speed-up x{walls[configs[0]] / walls[config]:.2f}"
        )
    local = [c for c in configs if c[0] == "local"]
    speedup = walls[local[0]] / walls[local[-1]]
    if speedup < options.min_speedup:
        print(f"speed-up x{speedup:.2f} is below --min-speedup {options.min_speedup}")
        ok = False
    return ok


if __name__ == "__main__":  # spawned workers import this file: run only as a script
    sys.exit(0 if main(get_options()) else 1)

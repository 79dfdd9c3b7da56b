"""Wall and CPU time of every stage of ``macromicro run`` (the CPU time of this process and
its children, so SUMO's own processes count where a stage starts them).

    .venv/bin/python scripts/bench_run.py scenarios/ring_paper_section.toml --out DIR

Runs the same pipeline as ``macromicro run SCENARIO --out DIR`` and prints one line per
stage, then writes ``DIR/bench_run.json`` (stage -> wall_s, cpu_s) and the load average
before and after, so that two runs compared side by side say what load they ran under.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import time
from pathlib import Path
from typing import Any

from macromicro_sumo.cli import main as cli_main
from macromicro_sumo.pipeline import build


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and its reaped children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def main(argv: list[str] | None = None) -> int:
    """Run the pipeline with per-stage wall and CPU clocks; returns the CLI's exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    clocks: dict[str, dict[str, float]] = {}
    original = build.run_stages

    def timed(stage: build.Stage) -> build.Stage:
        def run() -> Any:
            w0, c0 = time.perf_counter(), _cpu_s()
            try:
                return stage.run()
            finally:
                clocks[stage.name] = {
                    "wall_s": round(time.perf_counter() - w0, 2),
                    "cpu_s": round(_cpu_s() - c0, 2),
                }

        return dataclasses.replace(stage, run=run)

    def run_stages(sc: Any, stages: list[build.Stage], *rest: Any) -> dict[str, Any]:
        return original(sc, [timed(s) for s in stages], *rest)

    # The pipeline records each stage's wall and CPU seconds itself where it can run
    # stages in worker processes (wrapping them would keep them in this one).
    own_clocks = hasattr(build, "default_jobs")  # pipeline.parallel's, since 74609d0
    if not own_clocks:
        build.run_stages = run_stages
    load0 = os.getloadavg()
    w0, c0 = time.perf_counter(), _cpu_s()
    code = cli_main(["run", args.scenario, "--out", args.out])
    total = {"wall_s": round(time.perf_counter() - w0, 2), "cpu_s": round(_cpu_s() - c0, 2)}
    if own_clocks:
        manifest = json.loads(Path(args.out, "manifest.json").read_text())
        clocks = {
            name: {"wall_s": wall, "cpu_s": manifest["cpu_s"][name]}
            for name, wall in manifest["timings_s"].items()
            if name in manifest["cpu_s"]
        }
    result = {"stages": clocks, "total": total, "loadavg": [load0, os.getloadavg()]}
    for name, c in {**clocks, "total": total}.items():
        print(f"{name:32s} wall {c['wall_s']:8.1f} s   cpu {c['cpu_s']:8.1f} s")
    print(f"load average before {load0}, after {os.getloadavg()}")
    Path(args.out, "bench_run.json").write_text(json.dumps(result, indent=1) + "\n")
    return code


if __name__ == "__main__":
    raise SystemExit(main())

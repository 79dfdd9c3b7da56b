"""Batch runs: many scenario variants, each in its own output folder, on local worker
processes or on Ray.

Inputs are scenario files, globs, or a scenario with a ``[sweep]`` table, expanded into
the cartesian product of named variants (``batch/sweep.py``). Each stage is one function
for every scenario kind (``STAGES``: ``batch/tasks.py``); variants run on a backend of
``batch/backends.py``.

Layout of a batch folder ``DIR``::

    DIR/batch.json            the expanded spec (variants, their parameters, stages)
    DIR/batch_summary.csv     one row per variant: status, wall time, headline figures
    DIR/batch_macro.csv       every variant's macro statistics, parameters as columns
    DIR/batch_detectors.csv   every variant's per-detector intervals, parameters as columns
    DIR/variants/<name>/      one stage output folder per variant (SUMO's XML under sumo/)
    DIR/logs/<name>.log       what SUMO and the stage wrote to stderr

Faults: a variant runs into a hidden ``.partial-*`` folder that is renamed into place only
when every stage succeeded, so ``variants/<name>/manifest.json`` marks it complete. A failed
variant (bad file, SUMO error, killed worker) becomes a failed row; the others go on. A
re-run skips complete variants whose scenario and stages are unchanged and redoes the rest.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import json
import os
import secrets
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from macromicro_sumo.batch import export
from macromicro_sumo.batch.backends import RAY_INSTALL, LocalBackend, RayBackend
from macromicro_sumo.batch.sweep import Variant, expand
from macromicro_sumo.batch.tasks import STAGES, Outcome, Task
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import (
    OUTPUT_MARK,
    mark_output,
    out_lock,
    prepare_out_dir,
    write_json,
    write_text,
)

BACKENDS = ("local", "ray")
EXPORT_FORMATS = export.FORMATS


@dataclass
class BatchResult:
    out: Path
    summary: Any  # pandas DataFrame, one row per variant
    counts: dict[str, int]


def is_complete(folder: Path, variant: Variant, stages: Sequence[str]) -> bool:
    """Complete: renamed into place with its manifest, for the same scenario and stages."""
    if not (folder / "manifest.json").is_file() or not (folder / export.VARIANT_FILE).is_file():
        return False
    try:
        info = json.loads((folder / export.VARIANT_FILE).read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return (
        variant.scenario is not None
        and info.get("scenario_sha256") == variant.scenario.digest()
        and info.get("stages") == list(stages)
        and not export.damaged(folder)  # an output lost or cut short: redo the variant
    )


def _discard(partial: Path) -> None:
    """Remove an unfinished variant's folder and the stderr log beside it."""
    shutil.rmtree(partial, ignore_errors=True)
    partial.with_name(partial.name + ".log").unlink(missing_ok=True)


def run_batch(
    inputs: Sequence[str | Path],
    out: Path | str,
    stages: Sequence[str] = ("simulate",),
    workers: int = 1,
    backend: str = "local",
    address: str | None = None,
    progress: bool = True,
    command: str = "",
) -> BatchResult:
    """Run every variant of ``inputs`` into ``out``; re-runs skip complete variants."""
    from tqdm import tqdm

    if workers < 1:
        raise UserError(f"--workers {workers}: accepted >= 1")
    if backend not in BACKENDS:
        raise UserError(f"--backend {backend!r} is not accepted; accepted: {', '.join(BACKENDS)}")
    if address and backend != "ray":
        raise UserError("--address is for --backend ray")
    for stage in stages:
        if stage not in STAGES:
            raise UserError(f"unknown stage {stage!r}; accepted: {', '.join(STAGES)}")
    engine = LocalBackend(workers) if backend == "local" else RayBackend(workers, address)
    variants = expand(inputs)
    out = prepare_out_dir(out, [v.file for v in variants if v.file])
    vdir = out / "variants"
    vdir.mkdir(exist_ok=True)
    with out_lock(out):  # one batch (or run) per folder at a time
        for leftover in itertools.chain(vdir.glob(".partial-*"), vdir.glob(".trash-*")):
            if leftover.is_dir():
                shutil.rmtree(leftover, ignore_errors=True)
            else:
                leftover.unlink(missing_ok=True)
        spec = [
            {"name": v.name, "scenario": v.scenario_name, "file": v.file, "params": v.params}
            for v in variants
        ]
        # Parameters as [key, value] pairs: JSON objects are written with sorted keys, and the
        # sweep's own order is the order of the parameter columns.
        stored = [{**row, "params": list(row["params"].items())} for row in spec]
        write_json(
            {"stages": list(stages), "command": command, "variants": stored}, out / "batch.json"
        )

        statuses: dict[str, dict[str, Any]] = {}
        tasks, by_name = [], {v.name: v for v in variants}
        for v in variants:
            if v.error:
                statuses[v.name] = {"status": "failed", "error": v.error}
            elif is_complete(vdir / v.name, v, stages):
                info = json.loads((vdir / v.name / export.VARIANT_FILE).read_text())
                statuses[v.name] = {"status": "complete", "reused": True, "wall_s": info["wall_s"]}
            else:
                assert v.scenario is not None
                partial = vdir / f".partial-{v.name}.{secrets.token_hex(4)}"
                tasks.append(
                    Task(v.name, v.scenario, tuple(stages), str(partial), f"{command} [{v.name}]")
                )
        n_reused = sum(s["status"] == "complete" for s in statuses.values())
        n_invalid = sum(s["status"] == "failed" for s in statuses.values())
        bar = tqdm(
            total=len(variants),
            initial=n_reused + n_invalid,
            desc="batch",
            unit="variant",
            disable=not progress,
            dynamic_ncols=True,
        )

        def say(line: str) -> None:
            if progress:
                bar.write(line)

        say(
            f"batch: {len(variants)} variants, {n_reused} already complete, {n_invalid} invalid, "
            f"{len(tasks)} to run on {backend} with {workers} worker(s)"
        )
        for name, st in statuses.items():
            if st["status"] == "failed":
                say(f"  failed    {name}: {st['error']}")
                if not progress:
                    print(f"failed: {name}: {st['error']}", file=sys.stderr)

        headlines: dict[str, dict[str, Any]] = {}  # complete variants' figures, read once

        def write_tables(which: tuple[str, ...] = ("summary",)) -> None:
            tables = export.gather(spec, statuses, vdir, which, headlines)
            export.write_tables(tables, out, "batch", "csv")

        def done(task: Task, outcome: Outcome) -> None:
            partial, final = Path(task.out), vdir / task.name
            write_text(outcome.log, out / "logs" / f"{task.name}.log")
            if outcome.ok and final.exists() and not (final / OUTPUT_MARK).is_file():
                outcome = dataclasses.replace(
                    outcome,
                    ok=False,
                    error=f"{final}: exists and was not written by macromicro-sumo; move it away",
                )
            if outcome.ok:
                v = by_name[task.name]
                assert v.scenario is not None
                info = {
                    "variant": v.name,
                    "scenario_file": v.file,
                    "params": list(v.params.items()),
                    "stages": list(task.stages),
                    "scenario_sha256": v.scenario.digest(),
                    "wall_s": outcome.wall_s,
                    "backend": backend,
                    "host": outcome.host,
                }
                write_json(info, partial / export.VARIANT_FILE)
                mark_output(partial)
                if final.exists():  # stale: another scenario or other stages under this name
                    trash = vdir / f".trash-{task.name}.{secrets.token_hex(4)}"
                    os.replace(final, trash)
                    os.replace(partial, final)
                    shutil.rmtree(trash, ignore_errors=True)
                else:
                    os.replace(partial, final)
                statuses[task.name] = {"status": "complete", "wall_s": outcome.wall_s}
                say(f"  complete  {task.name}  ({outcome.wall_s:.1f} s)")
            else:
                _discard(partial)
                statuses[task.name] = {
                    "status": "failed",
                    "wall_s": outcome.wall_s,
                    "error": outcome.error,
                }
                say(f"  failed    {task.name}: {outcome.error}")
                if not progress:
                    print(f"failed: {task.name}: {outcome.error}", file=sys.stderr)
            bar.update(1)
            write_tables()

        try:
            engine.run(tasks, done)
        except BaseException:
            bar.close()
            for t in tasks:
                _discard(Path(t.out))
                if t.name not in statuses:  # it may have been renamed into place just now
                    final = vdir / t.name
                    done_now = is_complete(final, by_name[t.name], stages)
                    statuses[t.name] = {"status": "complete" if done_now else "interrupted"}
            with contextlib.suppress(Exception):
                write_tables(export.TABLES)
            raise
        bar.close()
        write_tables(export.TABLES)
    summary = export.gather(spec, statuses, vdir, ("summary",), headlines)["summary"]
    counts = summary["status"].value_counts().to_dict()
    counts["reused"] = n_reused
    return BatchResult(out, summary, counts)


# --------------------------------------------------------------------------- command line


def _cmd_batch(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    res = run_batch(
        args.scenarios,
        args.out,
        stages=args.stage or ["simulate"],
        workers=args.workers,
        backend=args.backend,
        address=args.address,
        progress=not args.quiet,
        command=args.command_line,
    )
    c = res.counts
    print(
        f"batch: {c.get('complete', 0)} complete ({c['reused']} reused), {c.get('failed', 0)} "
        f"failed in {time.perf_counter() - t0:.1f} s; see {res.out / 'batch_summary.csv'}"
    )
    return 1 if c.get("failed", 0) else 0


def _cmd_export(args: argparse.Namespace) -> int:
    for path in export.export(args.folder, args.format):
        print(f"wrote {path}")
    return 0


def register(sub: Any) -> None:
    """Add the ``batch`` and ``export`` subcommands to the CLI's subparsers."""
    p = sub.add_parser(
        "batch",
        help="run many scenario variants (files, globs or a [sweep]) in parallel",
        description="Run many scenario variants, each in its own folder under OUT/variants/, "
        "and gather their macro statistics in OUT/batch_macro.csv. Re-running skips "
        "complete variants. Exit code 1 when a variant failed.",
    )
    p.set_defaults(func=_cmd_batch)
    p.add_argument("scenarios", nargs="+", help="scenario TOML files or globs ('runs/*.toml')")
    p.add_argument("--out", type=Path, required=True, help="batch output folder")
    p.add_argument(
        "--stage",
        action="append",
        choices=list(STAGES),
        help="stage to run per variant, repeatable, in order (default: simulate)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1,
        help="parallel worker processes (local) or CPUs of the local Ray instance "
        "(default: CPUs available)",
    )
    p.add_argument("--backend", choices=BACKENDS, default="local", help="where variants run")
    p.add_argument("--address", help=f"Ray cluster address for --backend ray ({RAY_INSTALL})")
    p.add_argument("--quiet", action="store_true", help="no progress bar or status lines")

    p = sub.add_parser(
        "export",
        help="re-export a finished run or batch as CSV or Parquet tables",
        description="Write the macro, detector and summary tables of a finished batch "
        "(batch_*.FORMAT) or run (export_*.FORMAT) into its folder.",
    )
    p.set_defaults(func=_cmd_export)
    p.add_argument(
        "folder", type=Path, help="output folder of `macromicro batch`, `run` or `simulate`"
    )
    p.add_argument("--format", choices=EXPORT_FORMATS, default="csv", help="table format")
    p.add_argument("--quiet", action="store_true", help="accepted for symmetry; prints paths")

"""Time the joint refinement (``pipeline.refinement.refine``) of a finished run, and hash
what it writes: the same command on two trees (``PYTHONPATH=...``) says what a change of
the refinement saves and whether its outputs stay bit-identical.

    PYTHONPATH=. .venv/bin/python scripts/time_refine.py scenarios/netgen_corridor.toml RUN \\
        --out DIR [--set policy.refine_iterations=2 policy.driver_entry=auto ...]

RUN: a ``macromicro run`` folder (ground_truth/, generator/generator.pt, policy/policy.pt);
``--set``: scenario overrides (TABLE.KEY=VALUE, numbers typed); DIR must be new or empty.
Prints the refinement's wall and CPU time, those of its ``_episodes`` / ``section_episodes``
/ ``resolved_entry`` calls, and the SHA-256 of generator.pt's and policy.pt's tensors and of
refine_log.csv less its wall_s column.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path
from typing import Any

import pandas as pd
import torch

from macromicro_sumo.errors import UserError
from macromicro_sumo.pipeline import refinement
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.scenario.load import load_scenario


def _value(text: str) -> Any:
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _weights_hash(path: Path) -> str:
    """SHA-256 of the tensors in a checkpoint (keys and bytes, walked in order): paths and
    timings it records beside them are left out."""
    h = hashlib.sha256()

    def walk(obj: Any, key: str) -> None:
        if isinstance(obj, torch.Tensor):
            h.update(key.encode())
            h.update(obj.detach().cpu().contiguous().numpy().tobytes())
        elif isinstance(obj, dict):
            for k in sorted(obj, key=str):
                walk(obj[k], f"{key}/{k}")
        elif isinstance(obj, list | tuple):
            for i, v in enumerate(obj):
                walk(v, f"{key}/{i}")

    walk(torch.load(path, weights_only=True, map_location="cpu"), "")
    return h.hexdigest()[:16]


def _timed(name: str, fn: Any, spent: dict[str, list[tuple[float, float]]]) -> Any:
    """``fn`` that adds each call's wall time to ``spent[name]``."""

    def call(*args: Any, **kwargs: Any) -> Any:
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            took = (time.perf_counter() - t0, time.process_time() - c0)
            spent.setdefault(name, []).append(took)

    return call


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenario", type=Path)
    p.add_argument("run", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--set", nargs="*", default=[], metavar="TABLE.KEY=VALUE", dest="changes")
    args = p.parse_args(argv)
    try:
        overrides = {}
        for item in args.changes:
            key, sep, text = item.partition("=")
            if not sep or "." not in key:
                raise UserError(f"--set {item}: accepted: TABLE.KEY=VALUE")
            overrides[key] = _value(text)
        sc = load_scenario(args.scenario, overrides)
        if args.out.exists() and any(args.out.iterdir()):
            raise UserError(f"{args.out}: not empty; give a new folder")
        spent: dict[str, list[tuple[float, float]]] = {}
        for name in ("_episodes", "resolved_entry", "episode_inputs", "section_episodes"):
            if hasattr(refinement, name):
                setattr(refinement, name, _timed(name, getattr(refinement, name), spent))
        t0, c0 = time.perf_counter(), time.process_time()
        refinement.refine(
            sc,
            args.run / "ground_truth",
            args.run / "generator" / "generator.pt",
            args.run / "policy" / "policy.pt",
            args.out,
            progress=False,
            fit_prior=fit_residual_prior,
        )
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    # CPU time beside wall time: on a shared machine the wall clock measures the load too.
    print(f"refine wall {wall:.2f} s, cpu {cpu:.2f} s")
    for name, times in spent.items():
        w, c = (sum(t[i] for t in times) for i in (0, 1))
        print(f"  {name}: {len(times)} calls, wall {w:.2f} s, cpu {c:.2f} s")
    for name in ("generator.pt", "policy.pt"):
        print(f"  {name} weights sha256 {_weights_hash(args.out / name)}")
    log = pd.read_csv(args.out / "refine_log.csv").drop(columns=["wall_s"])
    print(
        f"  refine_log (less wall_s) sha256 {hashlib.sha256(log.to_csv().encode()).hexdigest()[:16]}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The whole pipeline in one call: ground truth -> generator (-> policy -> evaluation).

Each stage writes into its own sub-folder of ``out`` and is skipped when its manifest
already records the same scenario (digest) and seed, so an interrupted run resumes where
it stopped. Per-stage wall times go into ``out/manifest.json``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from macromicro_sumo.config import Scenario
from macromicro_sumo.files import prepare_out_dir, write_json
from macromicro_sumo.manifest import build_manifest


def _done(manifest: Path, sc: Scenario) -> bool:
    if not manifest.is_file():
        return False
    try:
        m = json.loads(manifest.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return m.get("scenario_sha256") == sc.digest() and m.get("seed") == sc.seed


def run(sc: Scenario, out: Path | str, command: str = "", progress: bool = True) -> dict[str, Any]:
    from macromicro_sumo.generator_train import run_train_generator
    from macromicro_sumo.ground_truth import simulate
    from macromicro_sumo.ppo import run_train_policy

    out = prepare_out_dir(out)
    gt, gen, pol = out / "ground_truth", out / "generator", out / "policy"
    stages: list[tuple[str, Path, Callable[[], Any]]] = [
        ("simulate", gt / "manifest.json", lambda: simulate(sc, gt, command, progress)),
        (
            "train_generator",
            gen / "generator_manifest.json",
            lambda: run_train_generator(sc, gt, gen, command, progress),
        ),
        (
            "train_policy",
            pol / "policy_manifest.json",
            lambda: run_train_policy(sc, gt, gen / "generator.pt", pol, True, command, progress),
        ),
    ]
    timings: dict[str, float | str] = {}
    for name, manifest, fn in stages:
        if _done(manifest, sc):
            timings[name] = "skipped (outputs exist for this scenario and seed)"
            if progress:
                print(f"[{name}] skipped: outputs exist for this scenario and seed")
            continue
        t0 = time.perf_counter()
        fn()
        timings[name] = round(time.perf_counter() - t0, 3)
        if progress:
            print(f"[{name}] done in {timings[name]:.1f} s")
    manifest = build_manifest(sc, command, stage="run")
    manifest["timings_s"] = timings
    write_json(manifest, out / "manifest.json")
    return manifest

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

from macromicro_sumo.evaluation.ring import evaluate
from macromicro_sumo.files import prepare_out_dir, write_json
from macromicro_sumo.generator.ring_train import run_train_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.pipeline.refinement import refine
from macromicro_sumo.policy.ppo import run_train_policy
from macromicro_sumo.report.ring import write_report
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.truth.ring import simulate

Stage = tuple[str, Path, Callable[[], Any]]  # name, its manifest, the function that runs it


def _done(manifest: Path, sc: Any) -> bool:
    if not manifest.is_file():
        return False
    try:
        m = json.loads(manifest.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return m.get("scenario_sha256") == sc.digest() and m.get("seed") == sc.seed


def policy_paths(pol: Path) -> dict[str, Path]:
    """The learned methods' checkpoints in a policy folder (the ablations when present)."""
    paths = {"policy": pol / "policy.pt"}
    for name in ("micro_only", "macro_only"):
        if (pol / f"policy_{name}.pt").is_file():
            paths[name] = pol / f"policy_{name}.pt"
    return paths


def standard_stages(
    out: Path,
    simulate: Callable[[Path], Any],
    train_generator: Callable[[Path, Path], Any],
    train_policy: Callable[[Path, Path, Path, str], Any],
    evaluate: Callable[[Path, Path, dict[str, Path], Path], Any],
) -> list[Stage]:
    """Ground truth -> generator -> the paper's policy and its two ablations -> evaluation,
    in ``out``'s sub-folders; the callables take the folders (and the policy's objective)."""
    gt, gen, pol, ev = out / "ground_truth", out / "generator", out / "policy", out / "evaluation"

    def train(objective: str) -> Callable[[], Any]:
        return lambda: train_policy(gt, gen / "generator.pt", pol, objective)

    return [
        ("simulate", gt / "manifest.json", lambda: simulate(gt)),
        ("train_generator", gen / "generator_manifest.json", lambda: train_generator(gt, gen)),
        ("train_policy", pol / "policy_manifest.json", train("mix")),
        ("train_policy_micro_only", pol / "policy_manifest_micro_only.json", train("micro_only")),
        ("train_policy_macro_only", pol / "policy_manifest_macro_only.json", train("macro_only")),
        (
            "evaluate",
            ev / "evaluation_manifest.json",
            lambda: evaluate(gt, gen / "generator.pt", policy_paths(pol), ev),
        ),
    ]


def run(sc: Scenario, out: Path | str, command: str = "", progress: bool = True) -> dict[str, Any]:
    out = prepare_out_dir(out)
    gt, gen, pol = out / "ground_truth", out / "generator", out / "policy"
    stages = standard_stages(
        out,
        lambda gt_: simulate(sc, gt_, command, progress),
        lambda gt_, gen_: run_train_generator(sc, gt_, gen_, command, progress),
        lambda gt_, g, pol_, obj: run_train_policy(sc, gt_, g, pol_, True, command, progress, obj),
        lambda gt_, g, pols, ev: evaluate(sc, gt_, g, pols, ev, command, progress),
    )
    if sc.policy.refine_iterations > 0:
        ref = out / "refined"
        stages += [
            (
                "refine",
                ref / "refine_manifest.json",
                lambda: refine(
                    sc, gt, gen / "generator.pt", pol / "policy.pt", ref, command, progress
                ),
            ),
            (
                "evaluate_refined",
                ref / "evaluation" / "evaluation_manifest.json",
                lambda: evaluate(
                    sc,
                    gt,
                    ref / "generator.pt",
                    {"policy": ref / "policy.pt"},
                    ref / "evaluation",
                    command,
                    progress,
                ),
            ),
        ]
    manifest = run_stages(sc, stages, out, command, progress)
    write_report(sc, out, manifest)
    return manifest


def run_stages(
    sc: Any, stages: list[Stage], out: Path, command: str, progress: bool
) -> dict[str, Any]:
    """Run (name, manifest path, function) stages in order, skipping those done for this
    scenario and seed; per-stage wall times go into ``out/manifest.json`` (returned)."""
    previous = _previous_timings(out / "manifest.json")
    timings: dict[str, Any] = {}
    for name, manifest, fn in stages:
        if _done(manifest, sc):
            timings[name] = previous.get(name, "skipped (outputs existed)")
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


def _previous_timings(path: Path) -> dict[str, Any]:
    """Stage timings of an earlier, interrupted or finished, run into the same folder."""
    try:
        return dict(json.loads(path.read_text()).get("timings_s", {}))
    except (OSError, json.JSONDecodeError):
        return {}

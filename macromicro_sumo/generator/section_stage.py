"""The ``train-generator`` stage of a section scenario (``run_train_section_generator``).

It splits the ground truth's runs (``stage_snapshots``), trains (``section_train``),
completes the held-out snapshots with the generator and the uniform baseline
(``section_sampler``, ``held_out_completion``) and writes their metrics
(``section_metrics``) and the manifest's summary.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import (
    HIDDEN_STREAM,
    SectionSnapshots,
    concat_snapshots,
    draw_k,
    hidden_per_snapshot,
    hide_random,
    recorded_snapshots,
    section_snapshots,
    snapshots_by_k,
    split_runs,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import prepare_out_dir, write_csv, write_stage_manifest
from macromicro_sumo.generator.pair_dynamics import pair_slope, recorded_pair_slope
from macromicro_sumo.generator.section_metrics import completion_metrics
from macromicro_sumo.generator.section_model import SectionGeneratorNet
from macromicro_sumo.generator.section_sampler import (
    SectionCompletion,
    complete_section,
    generated_length,
    k_of,
    uniform_completion,
)
from macromicro_sumo.generator.section_scene import Road
from macromicro_sumo.generator.section_train import (
    save_section_generator,
    train_section_generator,
)
from macromicro_sumo.generator.training import GENERATOR_FILES, GENERATOR_MANIFEST
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.truth.section import load_section_truth


def stage_snapshots(
    sc: SectionScenario, truth, splits: dict[str, np.ndarray]
) -> tuple[SectionSnapshots, SectionSnapshots, SectionSnapshots]:
    """(train, val, held-out) snapshots of the generator stage. With ``instrumented.hidden =
    "snapshot"``: K per snapshot from ``generator.hidden_train`` (training redraws them every
    epoch; validation keeps one seeded draw), and the held-out snapshots once at every K of
    ``generator.hidden_eval`` (``data.section.snapshots_by_k``)."""
    if not hidden_per_snapshot(sc):
        train = section_snapshots(truth, sc, splits["train"])
        val = section_snapshots(truth, sc, splits["val"]) if len(splits["val"]) else train
        return train, val, section_snapshots(truth, sc, splits["held_out"])
    cfg = sc.generator
    train = recorded_snapshots(truth, sc, splits["train"])
    val = recorded_snapshots(truth, sc, splits["val"]) if len(splits["val"]) else train
    rng = np.random.default_rng([sc.seed, HIDDEN_STREAM, 2])
    val = hide_random(val, draw_k(val, cfg.hidden_train, rng), rng)
    held = recorded_snapshots(truth, sc, splits["held_out"])
    by_k = snapshots_by_k(held, range(cfg.hidden_eval[0], cfg.hidden_eval[1] + 1), sc.seed)
    if not by_k:
        raise UserError(
            f"{truth.folder}: no held-out snapshot has {cfg.hidden_eval[0]} vehicles to hide "
            f"(generator.hidden_eval = {list(cfg.hidden_eval)})"
        )
    return train, val, concat_snapshots(list(by_k.values()))


def held_out_completion(
    method: str,
    net: SectionGeneratorNet,
    sc: SectionScenario,
    section: Section,
    held: SectionSnapshots,
    k: np.ndarray,
    seed: int,
    generated_length_m: float | None = None,
) -> SectionCompletion:
    """One completion of the held-out snapshots that the stage scores: the generator's as
    Stage II gets it (``generator_completion``: the braking bound, one step of reaction), so
    that the manifest's ``dropped`` counts the vehicles the pair check drops too (scored
    without it, the count stayed 0 where the envs' completions dropped some; with the
    generated vehicles' length, ``generated_length``); the uniform baseline's as it is."""
    args = (net, section, held, k, sc.generator.t_max, seed)
    if method == "uniform":
        return uniform_completion(*args)
    dt = sc.simulation.step_length_s
    return complete_section(*args, -sc.bounds.accel_mps2[0], dt, generated_length_m)


def _summary(g: pd.DataFrame, n_comp: int = 1) -> dict[str, Any]:
    """The manifest's figures of one method's held-out completions (``n_comp`` of each
    snapshot, pooled)."""
    return {
        "snapshots": int(len(g) // n_comp),
        "speed_err_vs_psi_mps": float(g["speed_err_vs_psi_mps"].mean()),
        "spacing_std_ratio": float(g["std_spacing_m"].mean() / g["true_std_spacing_m"].mean()),
        # sqrt of the mean variance: the pooled figure (the ring's generator metrics, and
        # what the evaluation's spacing std is on a loop, where every scene has one mean)
        "spacing_std_pooled_ratio": float(
            np.sqrt((g["std_spacing_m"] ** 2).mean() / (g["true_std_spacing_m"] ** 2).mean())
        ),
        "speed_std_ratio": float(g["std_speed_mps"].mean() / g["true_std_speed_mps"].mean()),
        "feasible_share": float(g["feasible"].mean()),
        "projections": int(g["projections"].sum()),
        "dropped": int(g["dropped"].sum()),
        "spread_slope": spread_slope(g, "std_spacing_m"),
        "true_spread_slope": spread_slope(g, "true_std_spacing_m"),
    }


def spread_slope(g: pd.DataFrame, column: str) -> float | None:
    """Least-squares slope of the scenes' spacing std (``column``: root mean variance per
    detector interval) on psi's spacing std across the intervals: about 1 for the truth, and
    for completions that follow the detectors' spread rather than the training runs' (a
    slope of 0.4-0.8 left held-out runs wider than the training runs 6-15% narrow: docs/
    design.md, "Spacing spread across seeds (stop 29)"). None with fewer than 3 intervals."""
    ok = g[np.isfinite(g["psi_std_spacing_m"]) & np.isfinite(g[column])]
    per = ok.groupby("psi_std_spacing_m")[column].apply(lambda x: np.sqrt((x**2).mean()))
    if len(per) < 3:
        return None
    return float(np.polyfit(per.index.to_numpy(dtype=float), per.to_numpy(dtype=float), 1)[0])


def run_train_section_generator(
    sc: SectionScenario, data: Path, out: Path, command: str = "", progress: bool = True
) -> dict[str, Any]:
    """CLI stage: split the ground truth's runs, train, evaluate on the held-out runs; write
    generator.pt, generator_train_log.csv, generator_metrics.csv (per held-out snapshot,
    generator and uniform baseline) and generator_manifest.json."""
    truth = load_section_truth(Path(data), sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    train, val, held = stage_snapshots(sc, truth, splits)
    out = prepare_out_dir(out)  # only once the inputs are known to be good
    t0 = time.perf_counter()
    net, log = train_section_generator(sc, truth.section, train, val, progress, out=out)
    train_s = time.perf_counter() - t0
    save_section_generator(out / "generator.pt", net, sc, {"epochs": len(log)})
    write_csv(log, out / "generator_train_log.csv")
    k = k_of(held, sc.generator.k_source)
    length = generated_length(truth)  # Stage II's generated vehicles'
    frames, timings = [], {"train_generator": round(train_s, 3)}
    first: dict[str, Any] = {}  # each method's first completion
    n_comp = sc.generator.eval_completions
    for method in ("generator", "uniform"):
        wall_s = 0.0
        for c in range(n_comp):  # the ring draws 4 per held-out scene: less sampling noise
            args = (method, net, sc, truth.section, held, k, sc.seed + c, length)
            comp = held_out_completion(*args)
            first.setdefault(method, comp)
            wall_s += comp.wall_s
            m = completion_metrics(truth.section, held, comp, k)
            if n_comp > 1:  # the column only where there are several (the CSV as before)
                m.insert(0, "completion", c)
            m.insert(0, "method", method)
            frames.append(m)
        timings[f"complete_{method}"] = round(wall_s, 3)
    metrics = pd.concat(frames, ignore_index=True)
    write_csv(metrics, out / "generator_metrics.csv")
    summary = {method: _summary(g, n_comp) for method, g in metrics.groupby("method")}
    if hidden_per_snapshot(sc):  # every held-out snapshot at every K: the ring's table
        for (method, k_true), g in metrics.groupby(["method", "k_true"]):
            summary[f"{method}_K{k_true}"] = _summary(g, n_comp)
        # How the completed scenes' spread will move once driven (generator/pair_dynamics.py):
        # the first generator completion's pairs per K beside the recorded scenes' own.
        road, gen_c = Road.of(truth.section), first["generator"]
        summary["truth_pair_slope"] = recorded_pair_slope(held, held.valid, road)
        for kv in np.unique(k):
            g = k == kv
            c = (gen_c.lane[g], gen_c.arc_m[g], gen_c.speed_mps[g], gen_c.valid[g])
            summary.setdefault(f"generator_K{kv}", {})["pair_slope"] = pair_slope(
                *c, gen_c.valid[g], road
            )
    manifest = build_manifest(sc, command, stage="train-section-generator")  # type: ignore[arg-type]
    manifest.update(
        ground_truth=str(data),
        splits={name: v.tolist() for name, v in splits.items()},
        epochs=len(log),
        best_val_loss=float(log["val_loss"].min()) if len(log) else None,
        timings_s=timings,
        summary=summary,
    )
    write_stage_manifest(manifest, out, GENERATOR_MANIFEST, GENERATOR_FILES)
    return manifest

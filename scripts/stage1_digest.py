"""Stage I's completions of a finished run, digested: did a generator change move them?

For a scenario and a run (its ground truth and trained generator.pt), completes (1) the
held-out snapshots as the train-generator stage scores them (``held_out_completion``, every
``generator.eval_completions`` seed) and (2) the train + val runs' snapshots as Stage II's
episode bank gets them (``generator_completion``, ``generator.k_source``), and prints per
part an md5 of the completed scenes (lane, arc, speed, valid, generated), the vehicles
generated and dropped, and the held-out metrics Stage I reports (speed error against psi,
spacing std ratio, projections, dropped). Run it from two worktrees (before / after) with
PYTHONPATH set to each: equal md5s mean the change leaves Stage I's output to the bit.

    PYTHONPATH=WT python scripts/stage1_digest.py TOML RUN [--json OUT.json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import section_snapshots, split_runs
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.generator.section_metrics import completion_metrics
from macromicro_sumo.generator.section_sampler import (
    generated_length,
    generator_completion,
    k_of,
)
from macromicro_sumo.generator.section_stage import held_out_completion, stage_snapshots
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth


def digest(*arrays: np.ndarray) -> str:
    h = hashlib.md5()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:10]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("run")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    run = Path(args.run)
    truth = load_section_truth(run / "ground_truth", sc)
    net = load_section_generator(run / "generator" / "generator.pt", sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    _, _, held = stage_snapshots(sc, truth, splits)
    k = k_of(held, sc.generator.k_source)
    out: dict[str, object] = {}
    parts, metrics = [], []
    t0 = time.perf_counter()
    for c in range(sc.generator.eval_completions):
        comp = held_out_completion(
            "generator", net, sc, truth.section, held, k, sc.seed + c, generated_length(truth)
        )
        parts.append(digest(comp.lane, comp.arc_m, comp.speed_mps, comp.valid, comp.generated))
        metrics.append(completion_metrics(truth.section, held, comp, k))
    m = pd.concat(metrics)
    out["held_out"] = {
        "md5": "/".join(parts),
        "snapshots": int(len(held)),
        "speed_err_vs_psi_mps": round(float(m["speed_err_vs_psi_mps"].mean()), 6),
        "spacing_std_ratio": round(
            float(m["std_spacing_m"].mean() / m["true_std_spacing_m"].mean()), 6
        ),
        "projections": int(m["projections"].sum()),
        "dropped": int(m["dropped"].sum()),
        "violations": int(m["violations"].sum()),
        "wall_s": round(time.perf_counter() - t0, 2),
    }
    t0 = time.perf_counter()
    runs = np.concatenate([splits["train"], splits["val"]])
    snaps = section_snapshots(truth, sc, runs)
    complete = generator_completion(
        net, truth.section, sc, sc.generator.k_source, sc.seed, typical_length(truth)
    )
    c = complete(snaps)
    out["bank"] = {
        "md5": digest(*c),
        "snapshots": int(len(snaps)),
        "generated": complete.generated,
        "dropped": complete.dropped,
        "wall_s": round(time.perf_counter() - t0, 2),
    }
    print(json.dumps(out))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""Regression: the paper ring's macro table may not change silently.

Runs the stages of ``macromicro run scenarios/ring_paper.toml`` that the ``policy`` and
``ground_truth`` rows of ``macro_alignment.csv`` depend on (ground truth, generator, the
``mix`` policy, the evaluation's rollouts on the held-out scenes: the same functions, seeds
and scenario file, so the rows equal those of ``runs/ring_paper/evaluation``) and compares
them with ``tests/pipeline/ring_macro_alignment_reference.csv``.

Tolerances (``TOLERANCE``): the ground truth replays SUMO deterministically and must match
to rounding; the policy rows allow float-level differences (another torch or BLAS build)
but stay well inside the spread over training seeds (``scripts/lf_seeds.py``: held-out
mean-speed error 0.008-0.025 m/s std across seeds), so a change of the method's results
fails. A deliberate change re-writes the reference:

    .venv/bin/python tests/pipeline/test_ring_regression.py --write

About 130 s on 2 cores (the generator and policy training dominate): a long training run,
so it runs in ``make test-slow``, not the default run (the ring's stages are in the default
run at small budgets: tests/pipeline/test_pipeline.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "scenarios" / "ring_paper.toml"
REFERENCE = Path(__file__).with_name("ring_macro_alignment_reference.csv")
METHODS = ("ground_truth", "policy")
COLUMNS = [
    "K",
    "method",
    "mean_speed_mps",
    "std_speed_mps",
    "mean_spacing_m",
    "std_spacing_m",
    "collisions",
    "episodes",
]
# column -> (absolute tolerance for ground_truth, absolute tolerance for policy)
TOLERANCE = {
    "mean_speed_mps": (1e-6, 2e-3),
    "std_speed_mps": (1e-6, 5e-3),
    "mean_spacing_m": (1e-4, 1e-4),
    "std_spacing_m": (1e-4, 0.15),
}


def ring_macro_rows(out: Path) -> pd.DataFrame:
    """The policy and ground-truth rows of the ring's macro table, computed in ``out``."""
    import torch

    from macromicro_sumo.data.ring import load_ground_truth, split_runs
    from macromicro_sumo.evaluation.ring import macro_alignment
    from macromicro_sumo.generator.ring_train import load_generator, run_train_generator
    from macromicro_sumo.policy.checkpoint import load_policy
    from macromicro_sumo.policy.stage import run_train_policy
    from macromicro_sumo.scenario.load import load_scenario
    from macromicro_sumo.truth.ring import simulate

    sc = load_scenario(SCENARIO)
    gt_dir, gen_dir, pol_dir = out / "ground_truth", out / "generator", out / "policy"
    simulate(sc, gt_dir, progress=False)
    run_train_generator(sc, gt_dir, gen_dir, progress=False)
    run_train_policy(sc, gt_dir, gen_dir / "generator.pt", pol_dir, progress=False, objective="mix")
    torch.set_num_threads(1)  # as the evaluate stage
    gt = load_ground_truth(gt_dir, sc)
    net = load_generator(gen_dir / "generator.pt", sc)
    agents = {"policy": load_policy(pol_dir / "policy.pt", sc)}
    held = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)["held_out"]
    lo, hi = sc.generator.hidden_eval
    align, _ = macro_alignment(sc, gt, net, agents, None, held, list(range(lo, hi + 1)))
    return align[align["method"].isin(METHODS)][COLUMNS].reset_index(drop=True)


@pytest.mark.slow
def test_ring_macro_table_matches_reference(tmp_path: Path) -> None:
    got = ring_macro_rows(tmp_path)
    ref = pd.read_csv(REFERENCE)
    assert list(got[["K", "method"]].itertuples(index=False)) == list(
        ref[["K", "method"]].itertuples(index=False)
    )
    np.testing.assert_array_equal(got["collisions"], ref["collisions"])
    np.testing.assert_array_equal(got["episodes"], ref["episodes"])
    is_gt = (got["method"] == "ground_truth").to_numpy()
    for col, (tol_gt, tol_policy) in TOLERANCE.items():
        tol = np.where(is_gt, tol_gt, tol_policy)
        diff = np.abs(got[col].to_numpy() - ref[col].to_numpy())
        bad = diff > tol
        assert not bad.any(), f"{col} moved beyond tolerance:\n" + got.loc[
            bad, ["K", "method", col]
        ].assign(reference=ref.loc[bad, col], tolerance=tol[bad]).to_string(index=False)


if __name__ == "__main__":
    import tempfile

    if sys.argv[1:] != ["--write"]:
        raise SystemExit(f"usage: python {sys.argv[0]} --write   (re-writes {REFERENCE})")
    with tempfile.TemporaryDirectory() as tmp:
        rows = ring_macro_rows(Path(tmp))
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    rows.to_csv(REFERENCE, index=False, float_format="%.6f")
    print(rows.to_string(index=False))

"""Regression: the paper ring's macro table may not change silently.

Runs the stages of ``macromicro run scenarios/ring_paper.toml`` that the ``policy`` and
``ground_truth`` rows of ``evaluation/macro_alignment_by_k.csv`` depend on (ground truth,
generator, the ``mix`` policy, the evaluation: the same functions, seeds and scenario file as
``make run``, so the rows equal those of ``runs/ring_paper/evaluation``) and compares them
with ``REFERENCE`` below.

Tolerances (``TOLERANCE``): the ground truth replays SUMO deterministically and must match
to rounding; the policy rows allow float-level differences (another torch or BLAS build)
but stay well inside the spread over training seeds, so a change of the method's results
fails. A deliberate change re-writes the reference: run

    .venv/bin/python tests/pipeline/test_ring_regression.py --write

and paste the block it prints over ``REFERENCE``.

A long training run (the whole generator and policy budgets of ring_paper), so it runs in
``make test-slow``, not the default run (the ring's stages are in the default run at small
budgets: tests/pipeline/test_pipeline.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "scenarios" / "ring_paper.toml"
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

# ``make run`` through the section stages with ring_paper's IDM prior (policy.prior = "idm"; its
# a refitted below the desired speed, the braking for a lower limit ahead the residual's),
# generator.lambda_pair = 0.1 and the pooled dispersion grouped by psi's spread, 27 Nov 2026
# (stop 29, `macromicro run scenarios/ring_paper.toml` at 12c1cdb), estimated-count rows of
# macro_alignment_by_k.csv.
REFERENCE: list[tuple] | None = [
    (1, "ground_truth", 12.005370, 0.494366, 125.663706, 32.732779, 0, 350),
    (2, "ground_truth", 12.005370, 0.494366, 125.663706, 32.732779, 0, 350),
    (3, "ground_truth", 12.005370, 0.494366, 125.663706, 32.732779, 0, 350),
    (4, "ground_truth", 12.005370, 0.494366, 125.663706, 32.732779, 0, 350),
    (1, "policy", 12.018946, 0.496280, 125.663706, 32.018659, 0, 350),
    (2, "policy", 12.026570, 0.485613, 125.663706, 32.950630, 0, 350),
    (3, "policy", 12.033804, 0.464565, 125.663706, 32.701327, 0, 350),
    (4, "policy", 12.045280, 0.449261, 125.663706, 32.662237, 0, 350),
]


def ring_macro_rows(out: Path) -> pd.DataFrame:
    """The policy and ground-truth rows of the ring's macro table by K, computed in ``out``."""
    from macromicro_sumo.evaluation.section import evaluate_section
    from macromicro_sumo.generator.section_stage import run_train_section_generator
    from macromicro_sumo.pipeline.build import fit_residual_prior
    from macromicro_sumo.policy.stage import run_train_policy
    from macromicro_sumo.scenario.load import load_scenario
    from macromicro_sumo.truth.section import simulate_section

    sc = load_scenario(SCENARIO)
    gt_dir, gen_dir, pol_dir = out / "ground_truth", out / "generator", out / "policy"
    simulate_section(sc, gt_dir, progress=False)
    run_train_section_generator(sc, gt_dir, gen_dir, progress=False)
    gen = gen_dir / "generator.pt"
    # policy.prior's fit as the pipeline passes it (make run's stage)
    run_train_policy(
        sc, gt_dir, gen, pol_dir, progress=False, objective="mix", fit_prior=fit_residual_prior
    )
    ev = out / "evaluation"
    evaluate_section(sc, gt_dir, gen, {"policy": pol_dir / "policy.pt"}, ev, progress=False)
    align = pd.read_csv(ev / "macro_alignment_by_k.csv")
    align = align[align["hidden_count"] == "estimated"] if "hidden_count" in align else align
    return align[align["method"].isin(METHODS)][COLUMNS].reset_index(drop=True)


@pytest.mark.slow
def test_ring_macro_table_matches_reference(tmp_path: Path) -> None:
    if REFERENCE is None:
        pytest.fail(
            "tests/pipeline/test_ring_regression.py: REFERENCE is not measured yet (TODO of "
            "stop 25); run it with --write and paste the rows"
        )
    got = ring_macro_rows(tmp_path)
    ref = pd.DataFrame(REFERENCE, columns=COLUMNS)
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
        raise SystemExit(f"usage: python {sys.argv[0]} --write   (prints REFERENCE's rows)")
    with tempfile.TemporaryDirectory() as tmp:
        rows = ring_macro_rows(Path(tmp))
    print("REFERENCE: list[tuple] | None = [")
    for r in rows.itertuples(index=False):
        vals = [f"{v:.6f}" if isinstance(v, float) else repr(v) for v in r]
        print(f"    ({', '.join(vals)}),")
    print("]")

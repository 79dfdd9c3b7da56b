"""The pipeline's road table for a section of a user's network (``SECTION``).

The same stages, skip and resume rules as on the ring (``pipeline.ring.run_pipeline``):
ground truth -> generator -> three policies (the paper's objective and its two ablations)
-> evaluation -> deployment -> report; this module names the section's stage functions,
the residual policy's prior fit and what the section does differently.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.evaluation.idm_fit import fit_policy_prior
from macromicro_sumo.evaluation.section import evaluate_section, micro_pairs
from macromicro_sumo.generator.section_train import run_train_section_generator
from macromicro_sumo.pipeline.ring import PipelineRoad, run_pipeline
from macromicro_sumo.report.write import write_report as write_section_report
from macromicro_sumo.truth.section import simulate_section


def fit_residual_prior(sc, truth, runs: np.ndarray) -> tuple[dict[str, float], dict[str, Any]]:
    """The model under a residual policy (``policy.prior``, "idm" or "gipps"), fitted to the
    observed pairs as the evaluation's idm_calibrated is (its pairs, runs and length), so the
    policy starts as that model and its residual is what training adds. Returns the agent's
    prior parameters and what the policy manifest records of the fit."""
    length = typical_length(truth)
    obs, acc = micro_pairs(sc, truth, runs)
    kind = sc.policy.prior
    prior, rmse = fit_policy_prior(kind, obs, acc, length, sc.simulation.step_length_s)
    return prior, {"prior": {"kind": kind, **prior, "fit_rmse_mps2": rmse, "pairs": len(acc)}}


SECTION = PipelineRoad(
    simulate_section,
    run_train_section_generator,
    evaluate_section,
    write_section_report,
    fit_prior=fit_residual_prior,
    # The K estimates of the ground truth are on the generator's snapshot grid.
    truth_reads=("generator.snapshot_every_s",),
    # Field data is deployed too: against the stations (deploy.field, deploy.compare).
)


def run_section(sc, out: Path | str, command: str = "", progress: bool = True) -> dict[str, Any]:
    """Every stage on a section scenario into ``out``; returns the run manifest."""
    return run_pipeline(sc, SECTION, out, command, progress)

"""The whole pipeline on a section of a user's network, stage by stage, resumable.

Same shape as ``pipeline.run`` on the ring, with the same stages and skip and resume rules
(``pipeline.ring.Stage``, ``RESUME``): ground truth -> generator -> three policies (the
paper's objective and its two ablations) -> evaluation -> deployment -> report.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.deploy.stage import deploy
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.evaluation.idm_fit import fit_policy_prior
from macromicro_sumo.evaluation.section import evaluate_section, micro_pairs
from macromicro_sumo.files import prepare_out_dir
from macromicro_sumo.generator.section_train import run_train_section_generator
from macromicro_sumo.pipeline.ring import run_stages, standard_stages
from macromicro_sumo.policy.stage import run_train_policy
from macromicro_sumo.report.deploy import make_deploy_plots
from macromicro_sumo.report.section import write_section_report
from macromicro_sumo.truth.section import simulate_section


def fit_idm_prior(sc, truth, runs: np.ndarray) -> tuple[dict[str, float], dict[str, Any]]:
    """The model under a residual policy (``policy.prior``, "idm" or "gipps"), fitted to the
    observed pairs as the evaluation's idm_calibrated is (its pairs, runs and length), so the
    policy starts as that model and its residual is what training adds. Returns the agent's
    prior parameters and what the policy manifest records of the fit."""
    length = typical_length(truth)
    obs, acc = micro_pairs(sc, truth, runs)
    kind = sc.policy.prior
    prior, rmse = fit_policy_prior(kind, obs, acc, length, sc.simulation.step_length_s)
    return prior, {"prior": {"kind": kind, **prior, "fit_rmse_mps2": rmse, "pairs": len(acc)}}


def run_section(sc, out: Path | str, command: str = "", progress: bool = True) -> dict[str, Any]:
    """Every stage on a section scenario into ``out``; returns the run manifest."""
    out = prepare_out_dir(out)
    stages = standard_stages(
        out,
        lambda gt: simulate_section(sc, gt, command, progress),
        lambda gt, gen: run_train_section_generator(sc, gt, gen, command, progress),
        lambda gt, g, pol, obj, resume: run_train_policy(
            sc, gt, g, pol, resume, command, progress, obj, fit_prior=fit_idm_prior
        ),
        lambda gt, g, pols, ev: evaluate_section(sc, gt, g, pols, ev, command, progress),
        # The K estimates of the ground truth are on the generator's snapshot grid.
        truth_reads=("generator.snapshot_every_s",),
        # Field data too: deployed against the stations (deploy.field, deploy.compare).
        deploy=lambda gt, pol, dep: deploy(
            sc, gt, pol, dep, command, progress, plots=make_deploy_plots
        ),
    )
    manifest = run_stages(sc, stages, out, command, progress)
    write_section_report(sc, out, manifest)
    return manifest

"""The whole pipeline on a section of a user's network, stage by stage, resumable.

Same shape as ``pipeline.run`` on the ring, with the same stages and skip and resume rules
(``pipeline.ring.Stage``, ``RESUME``): ground truth -> generator -> three policies (the
paper's objective and its two ablations) -> evaluation -> deployment -> report.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.deploy.stage import deploy
from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import (
    build_section_bank,
    recorded_min_gap,
    typical_length,
    typical_vclass,
)
from macromicro_sumo.evaluation.idm_fit import calibrate_idm
from macromicro_sumo.evaluation.section import evaluate_section, micro_pairs
from macromicro_sumo.files import prepare_out_dir
from macromicro_sumo.generator.section_sampler import generator_completion
from macromicro_sumo.generator.section_train import (
    load_section_generator,
    run_train_section_generator,
)
from macromicro_sumo.pipeline.ring import run_stages, standard_stages
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.policy.prior import idm_prior_params
from macromicro_sumo.policy.stage import open_policy_stage, write_policy_manifest
from macromicro_sumo.report.deploy import make_deploy_plots
from macromicro_sumo.report.section import write_section_report
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth, simulate_section


def run_train_section_policy(
    sc,
    data: Path,
    generator: Path,
    out: Path,
    resume: bool | str = False,
    command: str = "",
    progress: bool = True,
    objective: str | None = None,
) -> dict[str, Any]:
    """Stage II on a section: episodes from the train+val runs completed by the generator."""
    objective = objective or sc.policy.objective
    truth = load_section_truth(data, sc)
    net = load_section_generator(generator, sc)
    out, run_key, splits = open_policy_stage(
        sc, truth.runs, data, generator, out, objective, resume
    )
    snaps = section_snapshots(truth, sc, np.concatenate([splits["train"], splits["val"]]))
    complete = generator_completion(net, truth.section, sc, sc.generator.k_source, sc.seed)
    bank = build_section_bank(sc, truth, snaps, complete, sc.policy.horizon, sc.seed)
    net_file = scenario_inputs(sc).net_file
    vclass = typical_vclass(truth)
    min_gap = recorded_min_gap(truth)

    def make_core(bank_, seed: int, fcd_file: Path | None = None) -> SectionCore:
        # Replayed observed vehicles keep the recorded minGap in training as in evaluation
        # (Spreewaldring's race cars: 0 m, where the scenario's bound says 0.5 m).
        return SectionCore(
            sc,
            truth.section,
            bank_,
            net_file,
            seed=seed,
            fcd_file=fcd_file,
            vclass=vclass,
            replay_min_gap_m=min_gap,
        )

    # Demand episodes (policy.episodes): windows of the runs the policy trains on; the
    # validation runs stay out where they choose the checkpoint.
    demand_runs = splits["train"]
    if sc.policy.checkpoint_selection != "val_micro_logp":
        demand_runs = np.concatenate([splits["train"], splits["val"]])
    horizon = int(round(sc.policy.demand_horizon_s / sc.simulation.step_length_s))

    def make_demand() -> DemandCore:
        return DemandCore(sc, truth, demand_runs, horizon)

    prior, extra = None, {}
    if sc.policy.prior == "idm":
        # The same fit as the evaluation's idm_calibrated (its pairs, runs and length), so
        # the policy starts as that baseline and its residual is what training adds.
        length = typical_length(truth)
        obs, acc = micro_pairs(sc, truth, np.concatenate([splits["train"], splits["val"]]))
        idm, rmse = calibrate_idm(obs, acc, length)
        prior = idm_prior_params(idm.as_dict(), length)
        extra = {"prior": {"kind": "idm", **prior, "fit_rmse_mps2": rmse, "pairs": len(acc)}}
    res = train_policy(
        sc,
        bank,
        out,
        objective=objective,
        resume=resume,
        progress=progress,
        run_key=run_key,
        make_core=make_core,
        val_runs=splits["val"],
        make_demand=make_demand,
        prior_params=prior,
    )
    return write_policy_manifest(
        sc, command, objective, res, data, generator, out, episodes=len(bank), **extra
    )


def run_section(sc, out: Path | str, command: str = "", progress: bool = True) -> dict[str, Any]:
    """Every stage on a section scenario into ``out``; returns the run manifest."""
    out = prepare_out_dir(out)
    stages = standard_stages(
        out,
        lambda gt: simulate_section(sc, gt, command, progress),
        lambda gt, gen: run_train_section_generator(sc, gt, gen, command, progress),
        lambda gt, g, pol, obj, resume: run_train_section_policy(
            sc, gt, g, pol, resume, command, progress, obj
        ),
        lambda gt, g, pols, ev: evaluate_section(sc, gt, g, pols, ev, command, progress),
        # The K estimates of the ground truth are on the generator's snapshot grid.
        truth_reads=("generator.snapshot_every_s",),
        # A ground truth read from field files has no simulated runs to re-run with the
        # same seeds: its deployment would have to be compared with the field stations
        # themselves, which is not built yet (deploy refuses it in one line).
        deploy=None
        if sc.data.source == "files"
        else lambda gt, pol, dep: deploy(
            sc, gt, pol, dep, command, progress, plots=make_deploy_plots
        ),
    )
    manifest = run_stages(sc, stages, out, command, progress)
    write_section_report(sc, out, manifest)
    return manifest

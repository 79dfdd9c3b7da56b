"""The whole pipeline in one call: ground truth -> generator (-> policy -> evaluation ->
deployment) -> report.

``run_pipeline`` takes the table of stage functions (``PipelineRoad``: ``SECTION``, a section
of a network, the paper's ring among them) and builds the stages from it.

Each stage writes into its own sub-folder of ``out``. It is skipped when its manifest
records the scenario's values of every key that it, or a stage it reads from, depends on
(``Stage``: an edit of ``policy.eta`` redoes the policies and the evaluation, not the
ground truth or the generator) and no stage it reads from was redone in this call. An
interrupted run resumes where it stopped; a stage redone after an edit starts afresh over
the earlier run's checkpoints (``RESUME``). Per-stage wall times go into
``out/manifest.json``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.deploy.prior_score import deploy_prior
from macromicro_sumo.deploy.safety import AUTO_SIGMA, command_dawdle_sigma
from macromicro_sumo.deploy.stage import MANIFEST as DEPLOY_MANIFEST
from macromicro_sumo.deploy.stage import deploy
from macromicro_sumo.env.observed_drivers import krauss_pairs, observed_drivers
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.evaluation.driver_follow import (
    driver_gap_taus,
    driver_taus,
    driver_vtypes,
    pair_taus,
    tau_record,
    vtype_levels,
)
from macromicro_sumo.evaluation.idm_fit import MIN_PRIOR_PAIRS, fit_policy_prior
from macromicro_sumo.evaluation.krauss_fit import fit_krauss, network_defaults
from macromicro_sumo.evaluation.methods import LEARNED, checkpoint_name
from macromicro_sumo.evaluation.micro_data import keyed_micro_pairs
from macromicro_sumo.evaluation.section import evaluate_section
from macromicro_sumo.files import prepare_out_dir
from macromicro_sumo.generator.section_stage import run_train_section_generator
from macromicro_sumo.pipeline.parallel import default_jobs
from macromicro_sumo.pipeline.refinement import MANIFEST as REFINE_MANIFEST
from macromicro_sumo.pipeline.refinement import refine
from macromicro_sumo.pipeline.schedule import Stage, run_stages
from macromicro_sumo.policy.checkpoint import policy_file
from macromicro_sumo.policy.chosen_prior import (
    CHOICE_FILE,
    CHOICE_IGNORES,
    CHOICE_READS,
    choice_result,
    makes_choice,
)
from macromicro_sumo.policy.prior_choice import PriorFit, PriorScore
from macromicro_sumo.policy.stage import run_choose_prior, run_train_policy
from macromicro_sumo.report.deploy import make_deploy_plots
from macromicro_sumo.report.write import write_report
from macromicro_sumo.road.physics import leader_length_m, no_lower_limit_ahead
from macromicro_sumo.truth.section import simulate_section

# The one resume rule of the pipeline (``policy.checkpoint.resumable_checkpoint``): a
# stage's checkpoint of this very run is continued, one of another run (any input edited
# since) is ignored and replaced.
RESUME = "auto"

# Scenario keys no stage's outputs depend on: the scenario's label, and the objective of
# ``train-policy`` (the pipeline trains every objective); [deploy] is read by the deploy
# stage only (its own ignores: ``DEPLOY_IGNORES``).
_NOWHERE = ("name", "policy.objective", "deploy")
# Joint refinement's keys: inputs of the refine stage (and of the evaluation of what it
# refined), of no stage of the single pass.
_REFINE = (
    "policy.refine_iterations",
    "policy.refine_updates",
    "policy.refine_epochs",
    "policy.refine_lambda_rec",
)
_TRUTH_IGNORES = (*_NOWHERE, "generator", "policy", "evaluation")
# The deploy stage reads [deploy], the ground truth and the policies, not the evaluation.
DEPLOY_IGNORES = ("name", "policy.objective", "evaluation", *_REFINE)
_POLICY_IGNORES = (*_NOWHERE, "evaluation", *_REFINE)


def policy_paths(pol: Path) -> dict[str, Path]:
    """The learned methods' checkpoints in a policy folder (the ablations when present)."""
    paths = {"policy": pol / "policy.pt"}
    for method in LEARNED:
        if (pol / checkpoint_name(method)).is_file():
            paths[method.name] = pol / checkpoint_name(method)
    return paths


def standard_stages(
    out: Path,
    simulate: Callable[[Path], Any],
    train_generator: Callable[[Path, Path], Any],
    train_policy: Callable[[Path, Path, Path, str, bool | str], Any],
    evaluate: Callable[[Path, Path, dict[str, Path], Path], Any],
    truth_reads: tuple[str, ...] = (),
    deploy: Callable[[Path, Path, Path], Any] | None = None,
    choose_prior: Callable[[Path, Path], Any] | None = None,
) -> list[Stage]:
    """Ground truth -> generator -> the paper's policy and its two ablations -> evaluation
    (-> deployment), in ``out``'s sub-folders; the callables take the folders (and the
    policy's objective and the resume rule). ``truth_reads``: keys of the later stages'
    tables the ground truth reads too. ``choose_prior`` (ground truth, policy folder): the
    policies' prior chosen once, beside the generator (``policy.chosen_prior``), before
    the policy stages, which read it."""
    gt, gen, pol, ev = out / "ground_truth", out / "generator", out / "policy", out / "evaluation"
    upstream: tuple[str, ...] = ("simulate", "train_generator")
    choice: list[Stage] = []
    if choose_prior is not None:
        choice_file = pol / CHOICE_FILE
        choice.append(
            Stage(
                "choose_prior",
                choice_file,
                partial(choose_prior, gt, pol),
                needs=("simulate",),
                ignores=CHOICE_IGNORES,
                reads=CHOICE_READS,
                result=partial(choice_result, choice_file),
            )
        )
        upstream = (*upstream, "choose_prior")

    def train(objective: str) -> Callable[[], Any]:
        return partial(train_policy, gt, gen / "generator.pt", pol, objective, RESUME)

    # The paper's policy and its two ablations: (objective, keys it ignores besides).
    policies = {
        "train_policy": ("mix", ()),
        "train_policy_micro_only": ("micro_only", ("policy.eta",)),  # cloning: eta = 0
        "train_policy_macro_only": ("macro_only", ()),
    }
    stages = [
        Stage(
            "simulate",
            gt / "manifest.json",
            lambda: simulate(gt),
            ignores=_TRUTH_IGNORES,
            reads=truth_reads,
        ),
        Stage(
            "train_generator",
            gen / "generator_manifest.json",
            lambda: train_generator(gt, gen),
            needs=("simulate",),
            ignores=(*_NOWHERE, "policy", "evaluation"),
        ),
        *choice,
        *(
            Stage(
                name,
                pol / policy_file(objective, "manifest"),
                train(objective),
                needs=upstream,
                ignores=(*_POLICY_IGNORES, *ignores),
            )
            for name, (objective, ignores) in policies.items()
        ),
        Stage(
            "evaluate",
            ev / "evaluation_manifest.json",
            partial(_evaluate_job, evaluate, gt, gen / "generator.pt", pol, ev),
            needs=("simulate", "train_generator", *policies),
            ignores=(*_NOWHERE, *_REFINE),
        ),
    ]
    if deploy is not None:
        stages.append(
            Stage(
                "deploy",
                out / "deploy" / DEPLOY_MANIFEST,
                partial(deploy, gt, pol, out / "deploy"),
                needs=("simulate", *policies),
                ignores=DEPLOY_IGNORES,
            )
        )
    return stages


def refine_stages(
    out: Path,
    run_refine: Callable[[Path, Path, Path, Path], Any],
    evaluate: Callable[[Path, Path, dict[str, Path], Path], Any],
) -> list[Stage]:
    """Joint refinement (``policy.refine_iterations`` > 0) of the single pass's generator
    and policy, and the evaluation of the refined pair, in ``out/refined``; the callables
    take the folders as ``standard_stages``' do."""
    gt, ref = out / "ground_truth", out / "refined"
    return [
        Stage(
            "refine",
            ref / REFINE_MANIFEST,
            partial(
                run_refine,
                gt,
                out / "generator" / "generator.pt",
                out / "policy" / "policy.pt",
                ref,
            ),
            needs=("simulate", "train_generator", "train_policy"),
            ignores=(*_NOWHERE, "evaluation"),
        ),
        Stage(
            "evaluate_refined",
            ref / "evaluation" / "evaluation_manifest.json",
            partial(
                evaluate,
                gt,
                ref / "generator.pt",
                {"policy": ref / "policy.pt"},
                ref / "evaluation",
            ),
            needs=("simulate", "refine"),
            ignores=_NOWHERE,
        ),
    ]


def _evaluate_job(
    evaluate: Callable[[Path, Path, dict[str, Path], Path], Any],
    gt: Path,
    generator: Path,
    pol: Path,
    ev: Path,
) -> Any:
    """The evaluation stage: its policies are those in ``pol`` when it runs."""
    return evaluate(gt, generator, policy_paths(pol), ev)


def _policy_job(
    sc: Any,
    command: str,
    progress: bool,
    fit_prior: PriorFit | None,
    score_prior: PriorScore | None,
    *args: Any,
) -> Any:
    """A policy stage: ``args`` = (ground truth, generator, policy folder, objective,
    resume rule)."""
    gt, gen, pol, objective, resume = args
    return run_train_policy(
        sc,
        gt,
        gen,
        pol,
        resume,
        command,
        progress,
        objective,
        fit_prior=fit_prior,
        score_prior=score_prior,
    )


def _choice_job(
    sc: Any,
    command: str,
    progress: bool,
    fit_prior: PriorFit | None,
    score_prior: PriorScore | None,
    gt: Path,
    pol: Path,
) -> Any:
    """The prior's choice stage (``policy.stage.run_choose_prior``)."""
    return run_choose_prior(sc, gt, pol, command, progress, fit_prior, score_prior)


def _road_job(fn: Callable[..., Any], sc: Any, command: str, progress: bool, *args: Any) -> Any:
    """A road's stage function ``fn(sc, *folders, command, progress)``."""
    return fn(sc, *args, command, progress)


def _refine_job(
    sc: Any, command: str, progress: bool, fit_prior: PriorFit | None, *args: Any
) -> Any:
    """The refine stage: ``args`` = (ground truth, generator, policy, output folder)."""
    return refine(sc, *args, command, progress, fit_prior=fit_prior)


def _deploy_job(sc: Any, command: str, progress: bool, gt: Path, pol: Path, dep: Path) -> Any:
    return deploy(sc, gt, pol, dep, command, progress, plots=make_deploy_plots)


@dataclass(frozen=True)
class PipelineRoad:
    """The stages of the pipeline, each called as ``(sc, <its folders>, command, progress)``,
    and what the pipeline does besides."""

    simulate: Callable[..., Any]
    train_generator: Callable[..., Any]
    evaluate: Callable[..., Any]
    fit_prior: PriorFit | None = None  # policy.prior's IDM fit (policy.stage.run_train_policy)
    # policy.prior = "auto"'s deployment of a prior alone (policy.prior_choice)
    score_prior: PriorScore | None = None
    truth_reads: tuple[str, ...] = ()  # keys of later stages' tables the ground truth reads
    deploys: Callable[[Any], bool] = lambda sc: True  # noqa: E731


def run_pipeline(
    sc: Any,
    road: PipelineRoad,
    out: Path | str,
    command: str = "",
    progress: bool = True,
    jobs: int | None = None,
) -> dict[str, Any]:
    """Every stage of ``road`` on ``sc`` into ``out``, stages done before skipped
    (``Stage``), then the report; returns the run manifest. ``jobs``: processes for stages
    that can run side by side (None: ``parallel.default_jobs``; 1: one after the other)."""
    out = prepare_out_dir(out)
    stages = pipeline_stages(sc, road, out, command, progress)
    jobs = default_jobs() if jobs is None else jobs
    manifest = run_stages(sc, stages, out, command, progress, jobs)
    write_report(sc, out, manifest)
    return manifest


def pipeline_stages(
    sc: Any, road: PipelineRoad, out: Path, command: str = "", progress: bool = True
) -> list[Stage]:
    """``run_pipeline``'s stages of ``road`` on ``sc`` into ``out``: module-level functions
    and partials, so that a worker process can run any. The prior's choice is a stage of
    its own where the policy stages would each make it (``policy.chosen_prior``)."""
    fit, score = road.fit_prior, road.score_prior
    choose = None
    if makes_choice(sc) and fit is not None and score is not None:
        choose = partial(_choice_job, sc, command, progress, fit, score)
    stages = standard_stages(
        out,
        partial(_road_job, road.simulate, sc, command, progress),
        partial(_road_job, road.train_generator, sc, command, progress),
        partial(_policy_job, sc, command, progress, fit, score),
        partial(_road_job, road.evaluate, sc, command, progress),
        truth_reads=road.truth_reads,
        deploy=partial(_deploy_job, sc, command, progress) if road.deploys(sc) else None,
        choose_prior=choose,
    )
    if sc.policy.refine_iterations > 0:
        stages += refine_stages(
            out,
            partial(_refine_job, sc, command, progress, fit),
            partial(_road_job, road.evaluate, sc, command, progress),
        )
    return stages


def fit_residual_prior(
    sc, truth, runs: np.ndarray
) -> tuple[dict[str, float], dict[str, Any], tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    """The model under a section's residual policy (``policy.prior``), fitted to the
    observed pairs as the evaluation's idm_calibrated is (its pairs, runs and length; the
    Krauss form to its drivers' own: ``env.observed_drivers.prior_pairs``), so the policy
    starts as that model and its residual is what training adds. The Krauss form's
    parameters the pairs do not identify take SUMO's defaults for the network's vClass
    (``evaluation.krauss_fit.fit_krauss``; the manifest records which and why). Returns the
    agent's prior parameters, what the policy manifest records of the fit, and the pairs
    (the residual's likelihood pairs, ``policy.residual``: observations, accelerations and
    the Krauss form's each pair's driver's own tau, ``evaluation.driver_follow.pair_taus``,
    which ``policy.driver_follow`` hands the prior; None: the prior's one tau)."""
    # What the model subtracts from the leader column (a gap layout: nothing, the leader's
    # own length is in it; physics.leader_length_m).
    length = leader_length_m(sc.policy.observation, typical_length(truth))
    obs, acc, keys = keyed_micro_pairs(sc, truth, runs)
    kind = sc.policy.prior
    dt, record, pairs, taus = sc.simulation.step_length_s, {}, len(acc), None
    if kind == "krauss":  # guarded: the parameters the pairs do not identify fall back
        closed = truth.section.closed
        drivers = observed_drivers(sc, truth, runs)
        fit_obs, fit_acc, ratios = krauss_pairs(
            sc, truth, runs, obs, acc, own_median=closed, drivers=drivers
        )
        # No drivers' ratios identified: no desired speed either (both SUMO's defaults); on
        # an open section only, where the free term also fits drivers held back by what the
        # pairs do not show (a queue beyond the end, a merge: game/ramp fitted 0.82). A closed
        # one has nothing beyond it: ring_two_lane's fitted 0.92 (its IDM cars cruise below
        # their desired speed) took the deployed policy 0.77-1.04 -> 0.50-0.56 m/s
        # (docs/deploy-log.md, "ring_two_lane (stop 29)").
        held = ratios.fallback and not closed
        fixed = {"speed_factor": ratios.fallback} if held else None
        defaults, sigma = network_defaults(truth.vtypes), relax_dawdle(sc, truth)
        fit = fit_krauss(fit_obs, fit_acc, length, dt, defaults, fixed, dawdle_sigma=sigma)
        prior, rmse, record = fit.prior_params(length, dt), fit.rmse_mps2, fit.record()
        record["driver_ratios"] = ratios.record()
        # The observed drivers' own taus beside the prior's one (evaluation.driver_follow).
        own = driver_taus(drivers.obs, drivers.accel, drivers.keys, fit.params, length, dt)
        # policy.driver_follow = "by_vtype": each vType's quantiles too; "by_vtype_gap":
        # each vType's of the taus its drivers keep (driver_gap_taus).
        follow = sc.policy.driver_follow
        vtypes = driver_vtypes(truth, own) if follow.startswith("by_vtype") else None
        record["driver_taus"] = tau_record(own, fit.params, vtypes)
        if follow == "by_vtype_gap":
            kept = driver_gap_taus(drivers.obs, drivers.accel, drivers.keys, fit.params, length)
            by = vtype_levels(kept, driver_vtypes(truth, kept))
            record["driver_taus"]["by_vtype_gap"] = by
        taus = pair_taus(sc, keys, own, record["driver_taus"]["levels_s"])
        pairs = len(fit_acc)
    else:
        prior, rmse = fit_policy_prior(kind, obs, acc, length, dt)
        if kind == "idm":  # the pairs its fit took (fit_policy_prior's rule)
            keep = int(no_lower_limit_ahead(obs).sum())
            pairs = keep if keep >= MIN_PRIOR_PAIRS else pairs
    extra = {"prior": {"kind": kind, **prior, "fit_rmse_mps2": rmse, "pairs": pairs, **record}}
    return prior, extra, (obs, acc, taus)


def relax_dawdle(sc: Any, truth: Any) -> float:
    """The sigma a fallen-back Krauss a's relaxation is refitted at (``policy.relax_refit``
    "dawdled"): the deployment's command dawdle on this section (``deploy.command_dawdle``:
    "auto", a number, or "signals" where the truth recorded signals), else 0."""
    if sc.policy.relax_refit != "dawdled":
        return 0.0
    signals = getattr(truth, "signals", None)
    lights = signals is not None and not signals.empty
    sigma = command_dawdle_sigma(sc.deploy.command_dawdle, lights)
    return AUTO_SIGMA if sigma == "auto" else float(sigma)


SECTION = PipelineRoad(
    simulate_section,
    run_train_section_generator,
    evaluate_section,
    fit_prior=fit_residual_prior,
    score_prior=deploy_prior,
    # The K estimates of the ground truth are on the generator's snapshot grid.
    truth_reads=("generator.snapshot_every_s",),
)

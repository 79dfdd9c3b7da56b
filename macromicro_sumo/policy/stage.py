"""Stage II as a CLI stage: ``train-policy`` for every scenario, and what it is made of.

``run_train_policy``: episodes from the train + val runs completed by the generator (the
snapshots' bank, the env cores PPO runs on them, the demand episodes), then PPO
(``policy.ppo``).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from macromicro_sumo.data.section import section_snapshots, split_runs
from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.driver_speed import (
    EntryChoice,
    drivers_bank,
    entry_record,
    resolved_entry,
)
from macromicro_sumo.env.observed_drivers import driver_ratios
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import (
    build_section_bank,
    recorded_min_gap,
    typical_length,
    typical_vclass,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import (
    file_sha256,
    prepare_out_dir,
    write_stage_manifest,
)
from macromicro_sumo.generator.section_sampler import (
    generator_completion as section_completion,
)
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.checkpoint import policy_file, resumable_checkpoint
from macromicro_sumo.policy.chosen_prior import (
    CHOICE_FILE,
    apply_choice,
    makes_choice,
    read_choice,
    write_choice,
)
from macromicro_sumo.policy.driver_follow import follow_choice
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.policy.prior_choice import (
    FittedPrior,
    PriorDeploy,
    PriorFit,
    PriorScore,
    choose_prior,
    fit_family,
    with_prior,
)
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth


@dataclass(frozen=True)
class Episodes:
    """What PPO trains on: the episode bank, and the env cores over it."""

    bank: Any
    make_core: Callable[[Any, int], Any]
    make_demand: Callable[[], DemandCore] | None = None
    # The observed drivers' desired-speed ratio quantiles (``policy.driver_speed``).
    driver_speed: np.ndarray | None = None
    # policy.driver_entry "auto" resolved (None: set explicitly), for the manifest.
    entry: EntryChoice | None = None


def policy_run_key(sc, data: Path, generator: Path, objective: str) -> str:
    """What a resumable checkpoint must belong to: scenario, ground truth, generator, objective."""
    return hashlib.sha256(
        f"{sc.digest()}|{file_sha256(generator)}|{file_sha256(Path(data) / 'trajectories.csv')}|{objective}".encode()
    ).hexdigest()


def driver_speed_quantiles(sc: SectionScenario, truth, runs: np.ndarray) -> np.ndarray | None:
    """The observed drivers' desired-speed ratio quantiles (censoring-aware) the hidden ones
    draw from (``policy.driver_speed``); None where every driver takes the limits."""
    if sc.policy.driver_speed == "none":
        return None
    return driver_ratios(sc, truth, runs).quantiles


@dataclass(frozen=True)
class EpisodeInputs:
    """What ``section_episodes`` reads of the ground truth alone, the same for every
    generator: the train + val runs' snapshots, the scenario with ``policy.driver_entry``
    "auto" resolved, the observed drivers' desired-speed ratio quantiles (None: none), and
    what "auto" resolved to (None: set explicitly)."""

    snaps: Any
    drivers_sc: Any
    quantiles: np.ndarray | None
    entry: EntryChoice | None = None


def episode_inputs(sc: SectionScenario, truth, splits: dict[str, np.ndarray]) -> EpisodeInputs:
    """``EpisodeInputs`` of ``splits``' train + val runs; each of the entry rule and the
    quantiles reads every recorded scene of the observed drivers."""
    runs = np.concatenate([splits["train"], splits["val"]])
    # policy.driver_entry "auto": the rule the observed drivers of these runs say, read by
    # the banks and the demand episodes as by the deployment (``resolved_entry``)
    drivers_sc, entry = resolved_entry(sc, truth, runs)
    return EpisodeInputs(
        section_snapshots(truth, sc, runs),
        drivers_sc,
        driver_speed_quantiles(sc, truth, runs),
        entry,
    )


def section_episodes(
    sc: SectionScenario,
    truth,
    net,
    splits: dict[str, np.ndarray],
    inputs: EpisodeInputs | None = None,
) -> Episodes:
    """A section policy's episodes: snapshots of the train + val runs completed by the
    generator, its cores, and its demand episodes (``policy.episodes``). ``inputs``:
    ``episode_inputs``' where the caller builds episodes for several generators (the joint
    refinement), read once."""
    inputs = episode_inputs(sc, truth, splits) if inputs is None else inputs
    snaps, drivers_sc, quantiles = inputs.snaps, inputs.drivers_sc, inputs.quantiles
    complete = section_completion(
        net, truth.section, sc, sc.generator.k_source, sc.seed, typical_length(truth)
    )
    bank = build_section_bank(sc, truth, snaps, complete, sc.policy.horizon, sc.seed)
    if quantiles is not None:  # each hidden driver its own desired speed
        bank = drivers_bank(drivers_sc, truth.section, bank, quantiles, sc.seed)
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
    if sc.policy.checkpoint_selection == "last":
        demand_runs = np.concatenate([splits["train"], splits["val"]])
    horizon = int(round(sc.policy.demand_horizon_s / sc.simulation.step_length_s))

    def make_demand() -> DemandCore:
        return DemandCore(drivers_sc, truth, demand_runs, horizon)

    return Episodes(bank, make_core, make_demand, quantiles, inputs.entry)


def fit_stage_prior(
    sc: SectionScenario,
    truth: Any,
    splits: dict[str, np.ndarray],
    fit_prior: PriorFit | None,
    deploy: PriorDeploy | None = None,
) -> tuple[SectionScenario, FittedPrior | tuple[None, dict[str, Any], None]]:
    """``policy.prior``'s model fitted to the train + val runs' observed pairs (``fit_prior``;
    none without it or with ``prior = "none"``): (the scenario with its family resolved,
    (its parameters, what the manifest records, the pairs)). ``deploy`` scores a prior
    alone on training runs: a Krauss relaxation time the pairs leave at its bound is chosen
    with it (``policy.relax_choice``; without it the bound stays), and ``prior = "auto"``
    chooses the family with it (``policy.prior_choice``), once: the returned scenario says
    which, and every stage after this one reads it from the checkpoint
    (``policy.checkpoint.trained_prior``). The policy stage and the joint refinement both
    fit it here; the refinement, without ``deploy``, takes the relaxation from the
    checkpoint, so both train on one prior."""
    auto = sc.policy.prior == "auto"
    if auto and (fit_prior is None or deploy is None):
        raise UserError(
            f"{sc.source}: policy.prior = 'auto' is chosen by the policy stage of a section "
            "(train-policy); accepted here: none, idm, gipps or krauss"
        )
    if sc.policy.prior == "none" or fit_prior is None:
        return sc, (None, {}, None)
    runs = np.concatenate([splits["train"], splits["val"]])
    if not auto:
        return sc, fit_family(sc, truth, runs, fit_prior, deploy)
    family, fitted = choose_prior(sc, truth, runs, fit_prior, deploy)
    return with_prior(sc, family), fitted


def stage_prior(
    sc: SectionScenario,
    truth: Any,
    data: Path,
    out: Path,
    splits: dict[str, np.ndarray],
    fit_prior: PriorFit | None,
    deploy: PriorDeploy | None,
    command: str = "",
) -> tuple[SectionScenario, FittedPrior | tuple[None, dict[str, Any], None]]:
    """``fit_stage_prior``'s result for a policy stage writing into ``out``: a prior whose
    choice deploys candidates (``policy.chosen_prior.CHOSEN``) is taken from ``out``'s
    ``prior_choice.json`` where that was made for ``sc`` on this ground truth (the
    pipeline's ``choose_prior`` stage, or the first stage run alone), else chosen here and
    written there for the next. The manifest's ``prior_choice`` says which."""
    if not (makes_choice(sc) and fit_prior is not None and deploy is not None):
        return fit_stage_prior(sc, truth, splits, fit_prior, deploy)
    path = out / CHOICE_FILE
    record = read_choice(path, sc, data)
    got = None if record is None else apply_choice(record, sc, path)
    made = got is None
    if got is None:
        t0 = time.perf_counter()
        got = fit_stage_prior(sc, truth, splits, fit_prior, deploy)
        write_choice(path, sc, data, got, time.perf_counter() - t0, command)
    trained, (prior, extra, pairs) = got
    extra["prior_choice"] = {"file": str(path), "made_by_this_stage": made}
    return trained, (prior, extra, pairs)


def run_choose_prior(
    sc: SectionScenario,
    data: Path,
    out: Path,
    command: str = "",
    progress: bool = True,
    fit_prior: PriorFit | None = None,
    score_prior: PriorScore | None = None,
) -> dict[str, Any]:
    """The pipeline's ``choose_prior`` stage: the policy stages' prior chosen once
    (``fit_stage_prior`` with the deployment of a prior alone), from the ground truth in
    ``data`` alone, into ``out/prior_choice.json`` (returned), which the policy and its
    ablations then read (``stage_prior``)."""
    if fit_prior is None or score_prior is None:
        raise UserError(f"{sc.source}: the prior's choice needs its fit and its deployment")
    t0 = time.perf_counter()
    truth = load_section_truth(data, sc)
    out = prepare_out_dir(out)
    torch.set_num_threads(1)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    runs = np.concatenate([splits["train"], splits["val"]])
    quantiles = driver_speed_quantiles(sc, truth, runs)
    deploy = PriorDeploy(score_prior, Path(data), quantiles, progress)
    fitted = fit_stage_prior(sc, truth, splits, fit_prior, deploy)
    return write_choice(
        out / CHOICE_FILE, sc, Path(data), fitted, time.perf_counter() - t0, command
    )


def run_train_policy(
    sc: SectionScenario,
    data: Path,
    generator: Path,
    out: Path,
    resume: bool | str = False,
    command: str = "",
    progress: bool = True,
    objective: str | None = None,
    fit_prior: PriorFit | None = None,
    score_prior: PriorScore | None = None,
) -> dict[str, Any]:
    """CLI stage: episodes from train+val runs completed by the generator, then PPO.
    ``fit_prior``: the model under a residual policy (``policy.prior``), fitted to the
    train + val runs' observed pairs; without it PPO refuses a prior. ``score_prior``: the
    deployment of a candidate prior alone, with which a Krauss relaxation the pairs leave
    at its bound and ``policy.prior = "auto"``'s family are chosen (``PriorDeploy``);
    without it the relaxation stays at its bound and "auto" is refused."""
    objective = objective or sc.policy.objective
    truth = load_section_truth(data, sc)
    net = load_section_generator(generator, sc)
    out, run_key, splits = open_policy_stage(
        sc, truth.runs, data, generator, out, objective, resume
    )
    episodes = section_episodes(sc, truth, net, splits)
    deploy = None
    if score_prior is not None:
        deploy = PriorDeploy(score_prior, Path(data), episodes.driver_speed, progress)
    trained, (prior, extra, pairs) = stage_prior(
        sc, truth, Path(data), out, splits, fit_prior, deploy, command
    )
    # policy.driver_follow: each driver's own tau, its quantiles (None: the prior's one).
    taus, follow = follow_choice(trained, extra.get("prior", {}), prior, deploy)
    if follow is not None:
        extra["driver_follow"] = follow
    res = train_policy(
        trained,
        episodes.bank,
        out,
        objective=objective,
        resume=resume,
        progress=progress,
        run_key=run_key,
        make_core=episodes.make_core,
        val_runs=splits["val"],
        make_demand=episodes.make_demand,
        prior_params=prior,
        recorded_pairs=pairs,
        driver_speed=episodes.driver_speed,
        driver_tau=taus,
    )
    if "warmup_states" in res:  # the warm-up anchors' states (policy.residual)
        extra["warmup_states"] = res["warmup_states"]
    if episodes.entry is not None:  # what "auto" trained with, and why (its meaning moved)
        extra["driver_entry"] = entry_record(episodes.entry)
    return write_policy_manifest(
        sc, command, objective, res, data, generator, out, episodes=len(episodes.bank), **extra
    )


def open_policy_stage(
    sc, runs: np.ndarray, data: Path, generator: Path, out: Path, objective: str, resume: bool | str
) -> tuple[Path, str, dict[str, np.ndarray]]:
    """The head of a policy stage: the output folder, the run key, and the
    run split. Checks a checkpoint to resume before anything is overwritten."""
    out = prepare_out_dir(out)
    run_key = policy_run_key(sc, data, generator, objective)
    resumable_checkpoint(out / f"policy_{objective}_checkpoint.pt", sc, run_key, resume)
    torch.set_num_threads(1)
    return out, run_key, split_runs(runs, sc.generator.held_out_fraction, sc.seed)


def write_policy_manifest(
    sc, command: str, objective: str, res: dict, data: Path, generator: Path, out: Path, **extra
) -> dict[str, Any]:
    """``policy_manifest[_objective].json`` of a policy stage; returned.
    Written last: the pipeline takes a stage with its manifest as done."""
    stage = "train-policy" if objective == "mix" else f"train-policy_{objective}"
    manifest = build_manifest(sc, command, stage=stage)
    manifest.update(
        timings_s={"train_policy": round(res["wall_s"], 3)},
        env_steps=res["env_steps"],
        **extra,
        ground_truth=str(data),
        generator=str(generator),
    )
    own = [policy_file(objective, kind) for kind in ("pt", "train_log")]
    write_stage_manifest(manifest, out, policy_file(objective, "manifest"), own)
    return manifest

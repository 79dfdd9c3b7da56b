"""Stage II as a CLI stage: ``train-policy`` for every scenario, and what it is made of.

``run_train_policy``: episodes from the train + val runs completed by the generator, PPO
(``policy.ppo``), then the road's held-out check. What differs between the ring (the IDM
fleet) and a section of a user's network (its demand) is one ``PolicyRoad`` each: how the
ground truth and the generator are read, the episodes and the env cores PPO runs on them,
and the held-out check (the ring's fleet mean speed per K).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.data.ring import load_ground_truth, split_runs
from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.driver_speed import drivers_bank, free_speed_ratios, ratio_quantiles
from macromicro_sumo.env.ring import RingCore, build_bank, generator_completion
from macromicro_sumo.env.rollout import rollout
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import (
    build_section_bank,
    recorded_min_gap,
    typical_vclass,
)
from macromicro_sumo.files import (
    file_sha256,
    prepare_out_dir,
    write_csv,
    write_stage_manifest,
)
from macromicro_sumo.generator.ring_train import load_generator
from macromicro_sumo.generator.section_sampler import (
    generator_completion as section_completion,
)
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.agent import policy_action
from macromicro_sumo.policy.checkpoint import policy_file, resumable_checkpoint
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth

# Fits ``policy.prior``'s model to the observed pairs of the given runs of a ground truth:
# (the agent's prior parameters, what the manifest records of the fit, the pairs (obs,
# accel) it was fitted on, which the residual's likelihood uses: ``policy.residual``). The
# fit is the evaluation's (a policy module may not import it): the pipeline passes it in.
PriorFit = Callable[
    [Any, Any, np.ndarray],
    tuple[dict[str, float], dict[str, Any], tuple[np.ndarray, np.ndarray]],
]


@dataclass(frozen=True)
class Episodes:
    """What PPO trains on: the episode bank, and the road's env cores (None: the ring's)."""

    bank: Any
    make_core: Callable[[Any, int], Any] | None = None
    make_demand: Callable[[], DemandCore] | None = None
    # The observed drivers' desired-speed ratio quantiles (``policy.driver_speed``).
    driver_speed: np.ndarray | None = None


def policy_run_key(sc, data: Path, generator: Path, objective: str) -> str:
    """What a resumable checkpoint must belong to: scenario, ground truth, generator, objective."""
    return hashlib.sha256(
        f"{sc.digest()}|{file_sha256(generator)}|{file_sha256(Path(data) / 'trajectories.csv')}|{objective}".encode()
    ).hexdigest()


def training_bank(sc: Scenario, gt, net, splits: dict[str, np.ndarray]):
    """The ring policy's episodes: train + val runs completed by the generator (scenario seed)."""
    return build_bank(
        sc,
        gt,
        np.concatenate([splits["train"], splits["val"]]),
        generator_completion(net, sc, sc.seed),
        sc.policy.hidden_train,
        sc.seed,
    )


def heldout_speed(sc: Scenario, gt, net, agent, held: np.ndarray) -> pd.DataFrame:
    """Per K: the fleet's mean speed on the held-out runs, policy-driven vs recorded."""
    rows, h = [], sc.policy.horizon
    for k in range(sc.generator.hidden_eval[0], sc.generator.hidden_eval[1] + 1):
        bank = build_bank(sc, gt, held, generator_completion(net, sc, sc.seed + k), k, sc.seed + k)
        core = RingCore(sc, bank, seed=sc.seed)
        try:
            ro = rollout(core, policy_action(agent), h, sc.seed + k)
        finally:
            core.close()
        v, v_gt = np.nanmean(ro.speed_mps), bank.replay_speed_mps[:, 1 : h + 1].mean()
        rows.append(
            {
                "K": k,
                "mean_speed_mps": v,
                "gt_mean_speed_mps": v_gt,
                "abs_error_mps": abs(v - v_gt),
                "collisions": ro.collisions,
                "episodes": len(bank),
            }
        )
    return pd.DataFrame(rows)


def section_episodes(sc: SectionScenario, truth, net, splits: dict[str, np.ndarray]) -> Episodes:
    """A section policy's episodes: snapshots of the train + val runs completed by the
    generator, its cores, and its demand episodes (``policy.episodes``)."""
    runs = np.concatenate([splits["train"], splits["val"]])
    snaps = section_snapshots(truth, sc, runs)
    complete = section_completion(net, truth.section, sc, sc.generator.k_source, sc.seed)
    bank = build_section_bank(sc, truth, snaps, complete, sc.policy.horizon, sc.seed)
    quantiles = None
    if sc.policy.driver_speed != "none":  # each hidden driver its own desired speed
        quantiles = ratio_quantiles(free_speed_ratios(sc, truth, runs))
        bank = drivers_bank(sc, truth.section, bank, quantiles, sc.seed)
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

    return Episodes(bank, make_core, make_demand, quantiles)


@dataclass(frozen=True)
class PolicyRoad:
    """What the policy stage does differently on a road kind: read the ground truth and the
    generator, build the training episodes, and check the policy on the held-out runs
    (``heldout(sc, truth, net, agent, runs)``, written as ``policy_heldout_speed``)."""

    load_truth: Callable[[Path, Any], Any]
    load_generator: Callable[[Path, Any], Any]
    episodes: Callable[[Any, Any, Any, dict[str, np.ndarray]], Episodes]
    heldout: Callable[[Any, Any, Any, Any, np.ndarray], pd.DataFrame] | None = None


RING = PolicyRoad(
    load_ground_truth,
    load_generator,
    lambda sc, gt, net, splits: Episodes(training_bank(sc, gt, net, splits)),
    heldout_speed,
)
SECTION = PolicyRoad(load_section_truth, load_section_generator, section_episodes)


def run_train_policy(
    sc: Scenario | SectionScenario,
    data: Path,
    generator: Path,
    out: Path,
    resume: bool | str = False,
    command: str = "",
    progress: bool = True,
    objective: str | None = None,
    fit_prior: PriorFit | None = None,
) -> dict[str, Any]:
    """CLI stage: episodes from train+val runs completed by the generator, PPO, held-out
    check. ``fit_prior``: the model under a residual policy (``policy.prior``), fitted to the
    train + val runs' observed pairs; without it PPO refuses a prior."""
    objective = objective or sc.policy.objective
    road = SECTION if isinstance(sc, SectionScenario) else RING
    truth = road.load_truth(data, sc)
    net = road.load_generator(generator, sc)
    out, run_key, splits = open_policy_stage(
        sc, truth.runs, data, generator, out, objective, resume
    )
    episodes = road.episodes(sc, truth, net, splits)
    prior, extra, pairs = None, {}, None
    if sc.policy.prior != "none" and fit_prior is not None:
        runs = np.concatenate([splits["train"], splits["val"]])
        prior, extra, pairs = fit_prior(sc, truth, runs)
    res = train_policy(
        sc,
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
    )
    align = None
    if road.heldout is not None:
        align = road.heldout(sc, truth, net, res["agent"], splits["held_out"])
        write_csv(align, out / policy_file(objective, "heldout_speed"))
    manifest = write_policy_manifest(
        sc, command, objective, res, data, generator, out, episodes=len(episodes.bank), **extra
    )
    return {"alignment": align, **manifest} if align is not None else manifest


def open_policy_stage(
    sc, runs: np.ndarray, data: Path, generator: Path, out: Path, objective: str, resume: bool | str
) -> tuple[Path, str, dict[str, np.ndarray]]:
    """The head of a policy stage (ring or section): the output folder, the run key, and the
    run split. Checks a checkpoint to resume before anything is overwritten."""
    out = prepare_out_dir(out)
    run_key = policy_run_key(sc, data, generator, objective)
    resumable_checkpoint(out / f"policy_{objective}_checkpoint.pt", sc, run_key, resume)
    torch.set_num_threads(1)
    return out, run_key, split_runs(runs, sc.generator.held_out_fraction, sc.seed)


def write_policy_manifest(
    sc, command: str, objective: str, res: dict, data: Path, generator: Path, out: Path, **extra
) -> dict[str, Any]:
    """``policy_manifest[_objective].json`` of a policy stage (ring or section); returned.
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
    own = [policy_file(objective, kind) for kind in ("pt", "train_log", "heldout_speed")]
    write_stage_manifest(manifest, out, policy_file(objective, "manifest"), own)
    return manifest

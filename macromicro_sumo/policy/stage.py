"""Stage II as a CLI stage: ``train-policy`` on the ring, and what every policy stage shares.

``run_train_policy`` (the ring): episodes from the train + val runs completed by the
generator, PPO (``policy.ppo``), then the held-out check of the fleet's mean speed per K.
``open_policy_stage`` and ``write_policy_manifest`` are the head and tail of a policy
stage, ring or section (``pipeline.section``).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.data.ring import load_ground_truth, split_runs
from macromicro_sumo.env.ring import RingCore, build_bank, generator_completion
from macromicro_sumo.env.rollout import rollout
from macromicro_sumo.files import (
    file_sha256,
    prepare_out_dir,
    write_csv,
    write_stage_manifest,
)
from macromicro_sumo.generator.ring_train import load_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.agent import policy_action
from macromicro_sumo.policy.checkpoint import policy_file, resumable_checkpoint
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.scenario.ring import Scenario


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


def run_train_policy(
    sc: Scenario,
    data: Path,
    generator: Path,
    out: Path,
    resume: bool | str = False,
    command: str = "",
    progress: bool = True,
    objective: str | None = None,
) -> dict[str, Any]:
    """CLI stage: episodes from train+val runs completed by the generator, PPO, held-out check."""
    objective = objective or sc.policy.objective

    net = load_generator(generator, sc)
    gt = load_ground_truth(data, sc)
    out, run_key, splits = open_policy_stage(sc, gt.runs, data, generator, out, objective, resume)
    bank = training_bank(sc, gt, net, splits)
    res = train_policy(
        sc,
        bank,
        out,
        objective=objective,
        resume=resume,
        progress=progress,
        run_key=run_key,
        val_runs=splits["val"],
    )
    # Held-out check of the target: fleet mean speed vs ground truth per K.
    align = heldout_speed(sc, gt, net, res["agent"], splits["held_out"])
    write_csv(align, out / policy_file(objective, "heldout_speed"))
    manifest = write_policy_manifest(sc, command, objective, res, data, generator, out)
    return {"alignment": align, **manifest}


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

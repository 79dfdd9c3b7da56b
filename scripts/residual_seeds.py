"""Spread of a section's deployed policy over PPO seeds (issue 17; docs/deploy-log.md, "Why two
trainings of the residual differed").

Trains the Stage II policy of a section scenario several times on one ground truth,
generator and episode bank, changing only ``policy.seed`` (PPO's own seed: the actor's
initialisation, episode draws and action noise; the scenario's ``seed`` is kept, so each
deployment re-runs the truth's own held-out runs, which ``deploy`` checks), and deploys each
with ``macromicro deploy --methods policy``. Prints one row per seed: the deployment's GEH
share, speed-within-5% share, speed RMSE and bias, and the training's r_micro per pair at
the first and last update and the final action std.

    python scripts/residual_seeds.py SCENARIO --data GT --generator GEN/generator.pt
        [--seeds 1 2 3] [--out /tmp/residual_seeds]

Measured 2026-11-26 on scenarios/netgen_corridor.toml (fresh truth and generator, seeds
1 2 3): docs/deploy-log.md.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from macromicro_sumo import cli
from macromicro_sumo.data.section import split_runs
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.policy.stage import section_episodes
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

SUMMARY = ["share_geh_below_5", "share_speed_within_5pct", "speed_rmse_mps", "speed_bias_mps"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenario", type=Path)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--generator", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--out", type=Path, default=Path("/tmp/residual_seeds"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    sc = load_scenario(args.scenario)
    truth = load_section_truth(args.data, sc)
    net = load_section_generator(args.generator, sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    episodes = section_episodes(sc, truth, net, splits)
    runs = np.concatenate([splits["train"], splits["val"]])
    prior, pairs = None, None
    if sc.policy.prior != "none":
        prior, _, pairs = fit_residual_prior(sc, truth, runs)
    rows = []
    for seed in args.seeds:
        out = args.out / f"seed{seed}"
        res = train_policy(
            dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, seed=seed)),
            episodes.bank,
            out / "policy",
            progress=False,
            make_core=episodes.make_core,
            val_runs=splits["val"],
            make_demand=episodes.make_demand,
            prior_params=prior,
            recorded_pairs=pairs,
        )
        deploy = out / "deploy"
        cli.main(
            [
                "deploy", str(args.scenario), "--quiet", "--policy", str(out / "policy"),
                "--data", str(args.data), "--out", str(deploy), "--methods", "policy",
            ]
        )  # fmt: skip
        summary = pd.read_csv(deploy / "deploy_summary.csv").iloc[0]
        log = res["log"]
        rows.append(
            {
                "seed": seed,
                **{k: summary[k] for k in SUMMARY},
                "r_micro_first": log[0]["r_micro_per_pair"],
                "r_micro_last": log[-1]["r_micro_per_pair"],
                "action_std_mps2": log[-1]["action_std_mps2"],
            }
        )
    print(pd.DataFrame(rows).round(3).to_string(index=False))


if __name__ == "__main__":
    main()

"""Spread of the learned policy's results over training seeds (issue 5, leader-follower).

Trains the Stage II policy several times on the same ground truth, generator and training
episodes, changing only the training seed (network initialisation, PPO's episode draws and
action noise), and evaluates every policy exactly as ``macromicro evaluate`` does:

* leader-follower tests (paper Fig. 3, ``evaluation.lf_trials`` stochastic trials per
  scenario, the same evaluation seed for every policy) with the stochastic follower, and
  once with the follower's mean action (no action noise: what the training seed alone does);
* optionally (``--speed``) the held-out fleet mean-speed error per K (``policy_heldout_speed``).

Training seed ``scenario.seed + i`` for i = 0..n-1: i = 0 is the policy of ``macromicro run``.

    python scripts/lf_seeds.py [--scenario scenarios/ring_paper.toml] [--run runs/ring_paper]
        [--seeds 5] [--objective mix micro_only] [--speed] [--out runs/lf_seeds]
        [--set policy.updates=150 ...]

``--set`` changes the scenario for training and evaluation alike; the generator of
``--run`` must still fit it (its signature is checked).

Writes ``lf_seeds.csv`` (one row per objective, training seed, scenario and follower),
``lf_seeds_summary.csv`` (mean, min, max over seeds), ``lf_mean_traces.csv`` (per training
seed, scenario and follower: the speed and gap averaged over trials at every step, with the
IDM follower's speed, to see where a follower departs from IDM), ``heldout_speed_seeds.csv`` with
``--speed``, and prints the summary table.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
import tomllib
from pathlib import Path

import pandas as pd
import torch
from macromicro_sumo.data.ring import load_ground_truth, split_runs
from macromicro_sumo.generator.ring_train import load_generator
from macromicro_sumo.scenario.ring import Scenario

from macromicro_sumo.evaluation.leader_follower import (
    LeaderProfile,
    mean_idm_params,
    method_summary,
    policy_follower,
    run_leader_follower,
)
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.policy.stage import heldout_speed, training_bank
from macromicro_sumo.scenario.load import load_scenario


def lf_rmse(sc: Scenario, agent) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Leader-follower summary (evaluation's protocol) of one policy, stochastic and mean,
    and the per-step mean over trials of each follower's speed (for the trace diagnosis)."""
    duration = sc.evaluation.lf_duration_s
    profile = LeaderProfile(duration_s=duration, hold_s=min(20.0, duration / 3))
    followers = {
        "stochastic": policy_follower(agent),
        "mean_action": policy_follower(agent, stochastic=False),
    }
    traces, summary = run_leader_follower(
        sc, followers, mean_idm_params(sc), sc.evaluation.lf_trials, sc.seed, profile
    )
    s = method_summary(summary)
    cols = ["follower_speed_mps", "idm_follower_speed_mps", "gap_m"]
    mean_trace = traces.groupby(["scenario", "method", "time_s"], sort=False)[cols].mean()
    return (
        s[s["method"] != "IDM"].rename(columns={"method": "follower"}),
        mean_trace.reset_index().rename(columns={"method": "follower"}),
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="scenarios/ring_paper.toml")
    ap.add_argument("--run", default="runs/ring_paper", help="a finished `macromicro run` folder")
    ap.add_argument("--seeds", type=int, default=5, help="training seeds")
    ap.add_argument("--objective", nargs="+", default=["mix"])
    ap.add_argument("--speed", action="store_true", help="also the held-out mean-speed error")
    ap.add_argument("--out", default="runs/lf_seeds")
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="scenario overrides for training, e.g. policy.updates=150 (TOML values)",
    )
    args = ap.parse_args(argv)

    overrides = {k: tomllib.loads(f"v = {v}")["v"] for k, v in (a.split("=", 1) for a in args.set)}
    sc = load_scenario(args.scenario, overrides)
    run = Path(args.run)
    gt = load_ground_truth(run / "ground_truth", sc)
    net = load_generator(run / "generator" / "generator.pt", sc)
    torch.set_num_threads(1)
    splits = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)
    # The training episodes of run_train_policy: built once with the scenario's own seed.
    bank = training_bank(sc, gt, net, splits)
    lf_rows, trace_rows, speed_rows = [], [], []
    for objective in args.objective:
        for i in range(args.seeds):
            seed = sc.seed + i
            t0 = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                res = train_policy(
                    dataclasses.replace(sc, seed=seed),
                    bank,
                    Path(tmp),
                    objective=objective,
                    progress=False,
                    val_runs=splits["val"],
                )
            agent = res["agent"].eval()
            lf, trace = lf_rmse(sc, agent)
            for frame in (lf, trace):
                frame.insert(0, "train_seed", seed)
                frame.insert(0, "objective", objective)
            lf_rows.append(lf)
            trace_rows.append(trace)
            if args.speed:
                sp = heldout_speed(sc, gt, net, agent, splits["held_out"])
                sp["speed_err_mps"] = sp["mean_speed_mps"] - sp["gt_mean_speed_mps"]
                sp = sp[["K", "speed_err_mps"]]
                sp.insert(0, "train_seed", seed)
                sp.insert(0, "objective", objective)
                speed_rows.append(sp)
            stoch = lf[lf["follower"] == "stochastic"].set_index("scenario")
            print(
                f"{objective} seed {seed}: RMSE acc {stoch.loc['accelerate', 'mean_rmse_vs_idm_mps']:.3f}"
                f" dec {stoch.loc['decelerate', 'mean_rmse_vs_idm_mps']:.3f} m/s"
                f" ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    per = pd.concat(lf_rows, ignore_index=True)
    per.to_csv(out / "lf_seeds.csv", index=False, float_format="%.6f")
    traces = pd.concat(trace_rows, ignore_index=True)
    traces.to_csv(out / "lf_mean_traces.csv", index=False, float_format="%.4f")
    g = per.groupby(["objective", "scenario", "follower"], sort=False)["mean_rmse_vs_idm_mps"]
    summary = g.agg(seeds="size", mean="mean", min="min", max="max").reset_index()
    coll = per.groupby(["objective", "scenario", "follower"], sort=False)["collisions"].sum()
    summary["collisions"] = coll.to_numpy()
    summary.to_csv(out / "lf_seeds_summary.csv", index=False, float_format="%.6f")
    print("\nleader-follower RMSE vs IDM over training seeds [m/s]")
    print(summary.to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    if speed_rows:
        sp = pd.concat(speed_rows, ignore_index=True)
        sp.to_csv(out / "heldout_speed_seeds.csv", index=False, float_format="%.6f")
        t = sp.groupby(["objective", "K"])["speed_err_mps"].agg(["mean", "std", "min", "max"])
        print("\nheld-out mean-speed error (method - ground truth) over training seeds [m/s]")
        print(t.to_string(float_format=lambda x: f"{x:+.4f}"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

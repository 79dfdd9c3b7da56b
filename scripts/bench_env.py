"""Benchmark the Stage II environment and PPO on the paper's ring (one core).

The ring is a ring file's closed one-lane section (``SectionCore``, as every scenario).
Prints, measured side by side in one run:
  * env steps/s of ``SectionCore`` on the ring's scenes (resets every H steps included,
    random actions; the issue's target: 10,000),
  * a bare libsumo loop making the same SUMO calls (``bench_section_env.bench_bare``), and
    the ratio of the two;
  * the gymnasium env's steps/s (info dicts included);
  * PPO throughput (env steps/s including updates) and the wall time of a full training.

    python scripts/bench_env.py [--scenario scenarios/ring_paper.toml] [--steps 20000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from bench_section_env import bench_bare, bench_core

from macromicro_sumo.data.section import section_snapshots, split_runs
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank
from macromicro_sumo.env.section_envs import SectionHiddenEnv, true_section_completion
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth, simulate_section


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scenario", default="scenarios/ring_paper.toml")
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-training", action="store_true")
    ap.add_argument("--skip-section", action="store_true", help="ring only")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    sc = load_scenario(args.scenario)
    with tempfile.TemporaryDirectory() as tmp:
        gt_dir = simulate_section(sc, Path(tmp) / "gt", progress=False)
        truth = load_section_truth(gt_dir, sc)
        runs = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["train"]
        snaps = section_snapshots(truth, sc, runs)
        h = sc.policy.horizon
        bank = build_section_bank(sc, truth, snaps, true_section_completion, h, sc.seed)
        net = scenario_inputs(sc).net_file
        core = SectionCore(sc, truth.section, bank, net, seed=sc.seed)
        env_r, bare_r = [], []
        try:
            for r in range(args.repeats):  # interleaved, so both see the same machine load
                env_r.append(bench_core(core, args.steps, np.random.default_rng(r)))
                bare_r.append(bench_bare(core, args.steps, np.random.default_rng(r)))
        finally:
            core.close()
        env_s, bare_s = float(np.median(env_r)), float(np.median(bare_r))
        print(
            f"ring: N = {sc.fleet.n_vehicles}, H = {h}, {args.steps} steps x {args.repeats} "
            "repeats (median)"
        )
        print(
            f"  env (SectionCore), resets incl.: {env_s:10,.0f} env-steps/s   (target: >= 10,000)"
        )
        print(f"  bare libsumo, same SUMO calls   : {bare_s:10,.0f} steps/s")
        print(f"  env cost / bare loop            : {bare_s / env_s:10.2f} x")

        env = SectionHiddenEnv(sc, gt_dir, None)
        env.reset(seed=0)
        t0 = time.perf_counter()
        rng = np.random.default_rng(0)
        for _ in range(args.steps // 2):
            _, _, term, trunc, _ = env.step(rng.uniform(-1.1, 0.5, 1).astype(np.float32))
            if term or trunc:
                env.reset()
        gym_s = (args.steps // 2) / (time.perf_counter() - t0)
        env.close()
        print(f"  gymnasium env (one hidden)      : {gym_s:10,.0f} env-steps/s")

        if not args.skip_training:
            t0 = time.perf_counter()
            res = train_policy(sc, bank, Path(tmp), progress=False)
            wall = time.perf_counter() - t0
            print(
                f"PPO: {sc.policy.updates} updates x {sc.policy.episodes_per_update} episodes "
                f"x {h} steps"
            )
            rate = res["env_steps"] / res["wall_s"]
            print(f"  throughput incl. updates        : {rate:10,.0f} env-steps/s")
            print(
                f"  full training wall time         : {wall:10.1f} s   (target: <= 300 s on 2 cores)"
            )
    if not args.skip_section:
        # The largest example section, in this process (libsumo reloads its one simulation).
        from bench_section_env import main as section_main

        print("largest example section (SUMO's Bremen motorway, multi-lane, open):")
        section_main(["--steps", str(max(1000, args.steps // 4)), "--repeats", str(args.repeats)])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

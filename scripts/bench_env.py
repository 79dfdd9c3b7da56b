"""Benchmark the Stage II environment and PPO on the paper's ring (one core).

The ring is a ring file's closed one-lane section. Prints, measured side by side in one
run (repeats interleaved, so every core sees the same machine load):
  * env steps/s of the old core, ``SectionCore`` (one scene per SUMO run), and of the new
    one, ``BatchedSectionCore`` (B scenes in one SUMO run of B net copies; an env step is
    one scene's step), on the ring's scenes with resets every H steps and random actions,
    their ratio and the issue's target (10,000). Each figure twice: per wall second, and
    per CPU second of this process (SUMO runs inside it through libsumo), which a shared,
    loaded machine does not depress;
  * the batched core with its stop-26 reset (remove + vehicle.add, ``reuse_vehicles=False``)
    against its reset by placing the vehicles on the road, and the median of their
    per-repeat ratios;
  * a bare libsumo loop making SectionCore's SUMO calls (``bench_section_env.bench_bare``),
    and the old core's ratio to it;
  * the gymnasium env's steps/s (info dicts included) and the batched gymnasium
    VectorEnv's (``SectionHiddenVectorEnv``; sub-env steps, autoreset steps included);
  * PPO throughput (env steps/s including updates) and the wall time of a full training.

    python scripts/bench_env.py [--scenario scenarios/ring_paper.toml] [--steps 20000]
        [--scenes 64] [--skip-training] [--skip-section]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from bench_section_env import bench_bare, run_core

from macromicro_sumo.data.section import section_snapshots, split_runs
from macromicro_sumo.env.batched import BatchedSectionCore
from macromicro_sumo.env.batched_envs import SectionHiddenVectorEnv
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank
from macromicro_sumo.env.section_envs import SectionHiddenEnv, true_section_completion
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth, simulate_section

TARGET = 10_000  # env-steps/s, issue 16


def timed(fn, *args) -> tuple[float, float]:
    """(env steps per wall second, per CPU second of this process) of ``fn(*args)``,
    which returns the steps it made."""
    t0, c0 = time.perf_counter(), time.process_time()
    steps = fn(*args)
    return steps / (time.perf_counter() - t0), steps / (time.process_time() - c0)


def run_batched(core: BatchedSectionCore, steps: int, rng: np.random.Generator) -> int:
    """Every scene starts a random episode, then H steps of random actions; repeat.
    Returns the scene-steps made (truncated scenes idle and are not counted)."""
    done = 0
    while done < steps:
        core.step(np.zeros((core.b, core.n)), rng.integers(len(core.bank), size=core.b))
        for _ in range(core.bank.horizon):
            done += int(core.step(rng.uniform(-1.0, 1.0, (core.b, core.n))).stepped.sum())
    return done


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scenario", default="scenarios/ring_paper.toml")
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenes", type=int, default=64, help="B of the batched core")
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
        batched = BatchedSectionCore(sc, truth.section, bank, net, args.scenes, seed=sc.seed)
        old_r, new_r, bare_r, insert_r = [], [], [], []
        try:
            for r in range(args.repeats):  # interleaved, so all see the same machine load
                old_r.append(timed(run_core, core, args.steps, np.random.default_rng(r)))
                bare_r.append(bench_bare(core, args.steps, np.random.default_rng(r)))
                batched.reuse_vehicles = False  # reset by remove + vehicle.add (stop 26)
                insert_r.append(timed(run_batched, batched, args.steps, np.random.default_rng(r)))
                batched.reuse_vehicles = True
                new_r.append(timed(run_batched, batched, args.steps, np.random.default_rng(r)))
        finally:
            batched.close()
            core.close()
        old_w, old_c = np.median(old_r, axis=0)
        new_w, new_c = np.median(new_r, axis=0)
        ins = np.array(insert_r)
        reuse_gain = np.median(np.array(new_r) / ins, axis=0)  # per repeat, then the median
        bare_s = float(np.median(bare_r))
        print(
            f"ring: N = {sc.fleet.n_vehicles}, H = {h}, {args.steps} steps x {args.repeats} "
            "repeats (median), resets every H steps included"
        )
        print(f"  {'env-steps/s':33s}  {'per wall s':>12s}  {'per CPU s':>12s}")
        print(f"  {'old: SectionCore, one scene':33s}: {old_w:12,.0f}  {old_c:12,.0f}")
        label = f"new: BatchedSectionCore, B = {args.scenes}"
        print(f"  {label:33s}: {new_w:12,.0f}  {new_c:12,.0f}")
        print(f"  {'new / old':33s}: {new_w / old_w:11.2f}x  {new_c / old_c:11.2f}x")
        ins_w, ins_c = np.median(ins, axis=0)
        print(f"  {'  reset by insertion (stop 26)':33s}: {ins_w:12,.0f}  {ins_c:12,.0f}")
        label = "  placed / inserted resets"
        print(f"  {label:33s}: {reuse_gain[0]:11.2f}x  {reuse_gain[1]:11.2f}x")
        met = ["met" if x >= TARGET else "NOT met" for x in (new_w, new_c)]
        print(
            f"  {f'target >= {TARGET:,}':33s}: {met[0]:>12s}  {met[1]:>12s}   (load "
            f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs: the wall figure is this "
            "machine's share)"
        )
        print(f"  {'bare libsumo, SectionCore calls':33s}: {bare_s:12,.0f}")
        print(f"  {'old core cost / bare loop':33s}: {bare_s / old_w:11.2f}x")

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
        print(f"  {'gymnasium env (one hidden)':33s}: {gym_s:12,.0f}")
        venv = SectionHiddenVectorEnv(args.scenes, sc, gt_dir, None)
        venv.reset(seed=0)
        t0, done = time.perf_counter(), 0
        while done < args.steps // 2:
            venv.step(rng.uniform(-1.1, 0.5, (args.scenes, 1)))
            done += args.scenes
        vec_s = done / (time.perf_counter() - t0)
        venv.close()
        label = f"gymnasium VectorEnv, {args.scenes} envs"
        print(f"  {label:33s}: {vec_s:12,.0f}   (autoreset steps included)")

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

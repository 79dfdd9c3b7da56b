"""Benchmark the Stage II environment and PPO on the paper's ring (one core).

Prints, measured side by side in one run:
  * env steps/s of ``RingCore`` (resets every H steps included, random actions),
  * a bare libsumo loop making the same SUMO calls (moveTo + setRouteID + limits at each
    reset; setSpeed for every vehicle, simulationStep and the subscription read per step),
    and the ratio of the two;
  * the gymnasium env's steps/s (info dicts included);
  * PPO throughput (env steps/s including updates) and the wall time of a full training.

    python scripts/bench_env.py [--scenario scenarios/ring_paper.toml] [--steps 20000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import libsumo
import numpy as np
import torch
from macromicro_sumo.data.ring import load_ground_truth, split_runs
from macromicro_sumo.env.ring import RingCore, build_bank
from macromicro_sumo.truth.ring import simulate

from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.scenario.load import load_scenario


def bench_core(core: RingCore, steps: int, horizon: int, rng: np.random.Generator) -> float:
    t0 = time.perf_counter()
    done = 0
    while done < steps:
        core.reset(int(rng.integers(len(core.bank))))
        k = int(core.hidden.sum())
        for _ in range(horizon):
            core.step(rng.uniform(-1.1, 0.5, k))
            done += 1
    return done / (time.perf_counter() - t0)


def bench_bare(core: RingCore, steps: int, horizon: int, rng: np.random.Generator) -> float:
    """The same libsumo calls as RingCore, with no Python-side modelling at all."""
    ids, geo, bank = core.ids, core.geo, core.bank
    lanes, edges = geo.lane_ids, geo.edge_ids
    t0 = time.perf_counter()
    done = 0
    while done < steps:
        ep = int(rng.integers(len(bank)))
        for lane, v in zip(lanes, bank.limits_mps[ep], strict=True):
            libsumo.lane.setMaxSpeed(lane, float(v))
        idx = geo.edge_index(bank.arc0_m[ep])
        pos = bank.arc0_m[ep] - geo.offsets_m[idx]
        for vid, e, p in zip(ids, idx, pos, strict=True):
            libsumo.vehicle.moveTo(vid, lanes[e], float(p))
            libsumo.vehicle.setRouteID(vid, f"r_{edges[e]}")
        speeds = bank.speed0_mps[ep]
        for t in range(horizon):
            for vid, v in zip(ids, bank.replay_speed_mps[ep, t + 1], strict=True):
                libsumo.vehicle.setSpeed(vid, float(v))
            libsumo.simulationStep()
            speeds = libsumo.vehicle.getAllSubscriptionResults()
            done += 1
    del speeds
    return done / (time.perf_counter() - t0)


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
        gt_dir = simulate(sc, Path(tmp) / "gt", progress=False)
        gt = load_ground_truth(gt_dir, sc)
        runs = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)["train"]
        bank = build_bank(
            sc, gt, runs, lambda s: (s.arc_m, s.speed_mps), sc.policy.hidden_train, sc.seed
        )
        h = sc.policy.horizon
        core = RingCore(sc, bank, seed=sc.seed)
        env_r, bare_r = [], []
        for r in range(args.repeats):  # interleaved, so both see the same machine load
            env_r.append(bench_core(core, args.steps, h, np.random.default_rng(r)))
            bare_r.append(bench_bare(core, args.steps, h, np.random.default_rng(r)))
        core.close()
        env_s, bare_s = float(np.median(env_r)), float(np.median(bare_r))
        print(
            f"ring: N = {sc.fleet.n_vehicles}, H = {h}, {args.steps} steps x {args.repeats} repeats (median)"
        )
        print(
            f"  env (RingCore), resets included : {env_s:10,.0f} env-steps/s   (target: >= 10,000)"
        )
        print(f"  bare libsumo, same SUMO calls   : {bare_s:10,.0f} steps/s")
        print(f"  env cost / bare loop            : {bare_s / env_s:10.2f} x")

        from macromicro_sumo.env.ring_envs import RingHiddenEnv

        env = RingHiddenEnv(sc, gt_dir, None)
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
                f"PPO: {sc.policy.updates} updates x {sc.policy.episodes_per_update} episodes x {h} steps"
            )
            print(
                f"  throughput incl. updates        : {res['env_steps'] / res['wall_s']:10,.0f} env-steps/s"
            )
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

"""Joint refinement: Algorithm 1's optional outer iterations (off by default).

Each iteration (1) completes training snapshots with the current generator and rolls the
current policy out for one step, (2) fine-tunes the generator on the next-step scenes with
the consistency term lambda_rec * L_rec between its completion of the observed vehicles at
t + 1 and the hidden states the policy produced (paper, eq. for L_gen), and (3) fine-tunes
the policy on scenes completed by the updated generator.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from macromicro_sumo.checkpoints import save_torch
from macromicro_sumo.data.ring import Snapshots, load_ground_truth, split_runs
from macromicro_sumo.env.ring import RingCore, build_bank, generator_completion
from macromicro_sumo.env.rollout import rollout
from macromicro_sumo.files import prepare_out_dir, write_json
from macromicro_sumo.generator.ring_train import load_generator, save_generator, train_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.agent import policy_action
from macromicro_sumo.policy.checkpoint import CHECKPOINT_FORMAT, load_policy, signature
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.scenario.ring import Scenario


def next_step_snapshots(sc: Scenario, bank, agent, seed: int) -> Snapshots:
    """The scenes one policy step after each episode start: observed vehicles as recorded,
    hidden ones as the policy drove them (the targets of L_rec)."""
    core = RingCore(sc, bank, seed=sc.seed)
    try:
        ro = rollout(core, policy_action(agent), 1, seed)
    finally:
        core.close()
    ok = np.isfinite(ro.arc_m[:, 0]).all(axis=1)
    idx = np.flatnonzero(ok)
    return Snapshots(
        run=bank.run[idx],
        time_s=bank.time_s[idx] + sc.simulation.step_length_s,
        arc_m=ro.arc_m[idx, 0],
        speed_mps=ro.speed_mps[idx, 0],
        psi=bank.psi[idx],
        hidden=bank.hidden[idx],
        length_m=sc.network.length_m,
        spacing_std_m=None if bank.spacing_std_m is None else bank.spacing_std_m[idx],
    )


def refine(
    sc: Scenario,
    data: Path,
    generator: Path,
    policy: Path,
    out: Path,
    command: str = "",
    progress: bool = True,
) -> dict[str, Any]:
    """Run ``policy.refine_iterations`` outer iterations; writes generator.pt and policy.pt."""
    t0 = time.perf_counter()
    out = prepare_out_dir(out)
    gt = load_ground_truth(data, sc)
    net, agent = load_generator(generator, sc), load_policy(policy, sc)
    torch.set_num_threads(1)
    splits = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)
    runs = np.concatenate([splits["train"], splits["val"]])
    sc_rec = dataclasses.replace(
        sc, generator=dataclasses.replace(sc.generator, lambda_rec=sc.policy.refine_lambda_rec)
    )
    history = []
    for it in range(sc.policy.refine_iterations):
        seed = sc.seed + 1000 + it
        bank = build_bank(
            sc, gt, runs, generator_completion(net, sc, seed), sc.policy.hidden_train, seed
        )
        nxt = next_step_snapshots(sc, bank, agent, seed)
        perm = np.random.default_rng(seed).permutation(len(nxt))
        n_val = max(1, len(nxt) // 7)
        res = train_generator(
            sc_rec,
            gt,
            prepare_out_dir(out / f"iter_{it}"),
            progress,
            given=(nxt.take(perm[n_val:]), nxt.take(perm[:n_val])),
            init=net.state_dict(),
            epochs=sc.policy.refine_epochs,
        )
        net = res["net"]
        bank = build_bank(
            sc, gt, runs, generator_completion(net, sc, seed + 1), sc.policy.hidden_train, seed + 1
        )
        pres = train_policy(
            sc,
            bank,
            out / f"iter_{it}",
            progress=progress,
            updates=sc.policy.refine_updates,
            init=agent.state_dict(),
            val_runs=splits["val"],
        )
        agent = pres["agent"]
        history.append(
            {
                "iteration": it,
                "generator_val_loss": res["best_val_loss"],
                "r_macro": pres["log"][-1]["r_macro"],
                "r_micro_per_pair": pres["log"][-1]["r_micro_per_pair"],
            }
        )
    save_generator(
        out / "generator.pt", net, sc, {"refined_iterations": sc.policy.refine_iterations}
    )
    save_torch(
        out / "policy.pt",
        {
            "format": CHECKPOINT_FORMAT,
            "signature": signature(sc),
            "state_dict": agent.state_dict(),
            "hidden_size": agent.hidden_size,
            "objective": "mix",
            "scenario": sc.to_dict(),
        },
    )
    manifest = build_manifest(sc, command, stage="refine")
    manifest.update(iterations=history, timings_s={"refine": round(time.perf_counter() - t0, 3)})
    write_json(manifest, out / "refine_manifest.json")
    return manifest

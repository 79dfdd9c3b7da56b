"""Joint refinement: Algorithm 1's optional outer iterations (``policy.refine_iterations``,
0 by default: the paper's case study is a single pass).

Each iteration, on the train + val runs' snapshots:

1. completes them with the current generator and rolls the current policy out for one
   step on the section env core (``SectionCore``: observed vehicles replay their records,
   hidden ones are driven by the policy);
2. fine-tunes the generator for ``refine_epochs`` on the scenes at t + 1 (observed vehicles
   as recorded, the hidden ones where the policy drove them) with L_gen = L_macro +
   ``refine_lambda_rec`` L_rec, L_rec between its completion and those hidden states
   (``generator.reconstruction``);
3. fine-tunes the policy for ``refine_updates`` PPO updates on scenes completed by the
   updated generator (``policy.stage.section_episodes``, ``policy.ppo.train_policy``).

Writes ``generator.pt`` and ``policy.pt`` (the formats of the generator and policy stages:
every command that takes those takes these), ``refine_log.csv`` (one row per iteration),
``iter_<i>/`` (each iteration's generator.pt, policy.pt and fine-tune logs) and
``refine_manifest.json`` (written last).
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.data.section import (
    SectionSnapshots,
    signal_stops,
    split_runs,
)
from macromicro_sumo.env.rollout import rollout
from macromicro_sumo.env.section_bank import SectionBank, with_future
from macromicro_sumo.files import atomic_path, prepare_out_dir, write_csv, write_stage_manifest
from macromicro_sumo.generator.reconstruction import mean_reconstruction, reconstruction_loss
from macromicro_sumo.generator.section_model import SectionGeneratorNet
from macromicro_sumo.generator.section_sampler import k_of
from macromicro_sumo.generator.section_scene import Road
from macromicro_sumo.generator.section_train import (
    load_section_generator,
    save_section_generator,
    train_section_generator,
)
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.agent import Agent, policy_action
from macromicro_sumo.policy.checkpoint import load_policy, policy_file
from macromicro_sumo.policy.chosen_prior import CHOICE_FILE, apply_choice, makes_choice, read_choice
from macromicro_sumo.policy.ppo import train_policy
from macromicro_sumo.policy.prior import PRIOR_KEYS, prior_buffer
from macromicro_sumo.policy.prior_choice import PriorFit, with_prior
from macromicro_sumo.policy.relax_choice import relax_unidentified
from macromicro_sumo.policy.stage import (
    EpisodeInputs,
    episode_inputs,
    fit_stage_prior,
    section_episodes,
)
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.truth.section import load_section_truth

MANIFEST = "refine_manifest.json"
FILES = ("generator.pt", "policy.pt", "refine_log.csv")
# Seed offsets of each iteration's draws (the policy's one-step rollout, L_rec's figures).
ROLLOUT_SEED, REC_SEED = 1000, 17


def next_step_snapshots(
    sc: SectionScenario,
    snaps: SectionSnapshots,
    bank: SectionBank,
    make_core: Any,
    agent: Agent,
    seed: int,
    signals: pd.DataFrame | None = None,
) -> SectionSnapshots:
    """The scenes one step after each episode's start (L_rec's targets): observed vehicles
    as recorded, hidden ones where the policy drove them (``bank`` completes ``snaps``, one
    episode each, in order), and the red or yellow stop lines of the truth's ``signals``
    (signals.csv) at that step, as every snapshot carries its own (standing leaders for
    the generator; the env ran the signals as recorded). Episodes the env cut short (a
    failed insertion) are left out, and so are those with no hidden vehicle left; a hidden
    vehicle may only be missing where it left an open section within the step.
    ``make_core(bank, seed)``: the policy stage's env core."""
    core = make_core(bank, seed)
    try:
        ro = rollout(core, policy_action(agent), 1, seed)
    finally:
        core.close()
    dt = sc.simulation.step_length_s
    hid = bank.hidden & bank.valid
    lane = np.where(hid, ro.lane[:, 0], bank.replay_lane[:, 1])
    arc = np.where(hid, ro.arc_m[:, 0], bank.replay_arc_m[:, 1])
    speed = np.where(hid, ro.speed_mps[:, 0], bank.replay_speed_mps[:, 1])
    valid = bank.valid & np.isfinite(arc) & np.isfinite(speed)
    # A hidden vehicle gone after one step: it left the section's open end, or the episode
    # failed (then the scene is not the policy's).
    gone = hid & ~valid
    if core.section.closed:
        failed = gone.any(axis=1)
    else:
        reach = bank.arc0_m + bank.speed0_mps * dt + 2 * max(-sc.bounds.accel_mps2[0], 1.0) * dt
        failed = (gone & (reach < core.section.length_m)).any(axis=1)
    keep = np.flatnonzero(~failed & (hid & valid).any(axis=1))
    observed = valid & ~hid
    vehicles_est = snaps.k_est + snaps.observed.sum(axis=1)  # the detectors' count at t
    stops = signal_stops(signals, bank.run, bank.time_s + dt) or (None, None)
    nxt = SectionSnapshots(
        run=bank.run,
        time_s=bank.time_s + dt,
        lane=np.where(valid, lane, 0).astype(np.int64),
        arc_m=np.where(valid, arc, 0.0),
        speed_mps=np.where(valid, speed, 0.0),
        length_m=bank.length_m,
        valid=valid,
        observed=observed,
        psi=bank.psi,
        k_true=(valid & hid).sum(axis=1),
        k_est=np.maximum(0, vehicles_est - observed.sum(axis=1)),
        stop_lane=stops[0],
        stop_arc_m=stops[1],
    )
    return nxt.take(keep)


def refine_prior(
    sc: SectionScenario,
    truth: Any,
    data: Path,
    policy: Path,
    agent: Agent,
    splits: dict,
    fit_prior: PriorFit | None,
) -> tuple[SectionScenario, Any]:
    """The prior the single pass trained ``agent`` (``policy``'s) on, as
    ``policy.stage.fit_stage_prior`` returns it: the fine-tune trains on it, nothing is
    chosen again. A prior the pipeline chooses once (``policy.chosen_prior.CHOSEN``) is read
    from ``prior_choice.json`` and its pairs beside ``policy`` where that file is fresh
    (``read_choice``: made for ``sc`` on the ground truth in ``data``) and is the one the
    checkpoint drives with (its family and parameters); else the checkpoint's family is
    fitted to the train + val runs' pairs again, its Krauss relaxation time taken from the
    checkpoint (the policy stage chose it by deployments of the prior alone)."""
    path = policy.parent / CHOICE_FILE
    if makes_choice(sc) and fit_prior is not None:
        record = read_choice(path, sc, data, "fitting the policy's prior again")
        if record is not None:
            got = apply_choice(record, sc, path)
            if got[0].policy.prior == agent.prior and _drives_with(agent, got[1][0]):
                got[1][1]["prior_choice"] = {"file": str(path), "made_by_this_stage": False}
                return got
            print(f"{path}: not the prior {policy} drives with; fitting the policy's prior again")
    trained = with_prior(sc, agent.prior) if sc.policy.prior == "auto" else sc
    trained, (prior, extra, pairs) = fit_stage_prior(trained, truth, splits, fit_prior)
    if prior is not None and agent.prior == "krauss" and relax_unidentified(prior):
        chosen = {"relax_s": prior_buffer(agent)["relax_s"]}
        if not relax_unidentified(chosen):  # the policy stage chose one below the bound
            prior["relax_s"] = extra["prior"]["relax_s"] = chosen["relax_s"]
    return trained, (prior, extra, pairs)


def _drives_with(agent: Agent, params: dict[str, float]) -> bool:
    """Whether ``agent``'s prior parameters (float32 buffers) are ``params``."""
    have = getattr(agent, f"{agent.prior}_prior").numpy()
    want = np.array([params[k] for k in PRIOR_KEYS[agent.prior]], dtype=have.dtype)
    return bool(np.array_equal(have, want))


def _snapshots(sc: SectionScenario, truth: Any, inputs: EpisodeInputs) -> SectionSnapshots:
    """The train + val runs' snapshots the policy stage's bank completes (those with the
    horizon's future recorded), in its order: the same every iteration."""
    snaps = inputs.snaps
    return snaps.take(with_future(truth, snaps, sc.policy.horizon, sc.simulation.step_length_s))


def _episodes(
    sc: SectionScenario,
    truth: Any,
    net: SectionGeneratorNet,
    splits: dict,
    inputs: EpisodeInputs | None = None,
):
    """The policy stage's episodes for ``net`` and the snapshots their bank completes
    (``inputs``: ``episode_inputs``' where the caller has them)."""
    inputs = episode_inputs(sc, truth, splits) if inputs is None else inputs
    ep = section_episodes(sc, truth, net, splits, inputs)
    snaps = _snapshots(sc, truth, inputs)
    if len(snaps) != len(ep.bank):  # the bank keeps exactly these snapshots, in order
        raise AssertionError(f"{len(snaps)} snapshots for {len(ep.bank)} episodes")
    return ep, snaps


def refine(
    sc: SectionScenario,
    data: Path,
    generator: Path,
    policy: Path,
    out: Path,
    command: str = "",
    progress: bool = True,
    fit_prior: PriorFit | None = None,
) -> dict[str, Any]:
    """``policy.refine_iterations`` outer iterations from the single pass's ``generator``
    and ``policy``; writes the refined generator.pt and policy.pt into ``out``. ``fit_prior``:
    the prior's fit (``policy.prior``) as the policy stage gets it; returns the manifest."""
    t0 = time.perf_counter()
    cfg = sc.policy
    truth = load_section_truth(Path(data), sc)
    net, agent = load_section_generator(generator, sc), load_policy(policy, sc)
    out = prepare_out_dir(out)
    torch.set_num_threads(1)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    # What the episodes read of the ground truth alone (the snapshots, policy.driver_entry
    # "auto" resolved, the drivers' speed quantiles), once: section_episodes would read the
    # observed drivers' every recorded scene twice at each of the 1 + 2 x iterations builds.
    inputs = episode_inputs(sc, truth, splits)
    ep0, snaps = _episodes(sc, truth, net, splits, inputs)
    trained, (prior, extra_manifest, pairs) = refine_prior(
        sc, truth, Path(data), Path(policy), agent, splits, fit_prior
    )
    # The fine-tune keeps each next-step scene's hidden set (the policy's vehicles): no
    # fresh hidden sets per epoch, as with instrumented.hidden = "run".
    fixed = dataclasses.replace(sc, instrumented=dataclasses.replace(sc.instrumented, hidden="run"))
    road = Road.of(truth.section)
    rec = ("L_rec", cfg.refine_lambda_rec, reconstruction_loss)
    rows = []
    for it in range(cfg.refine_iterations):
        folder = prepare_out_dir(out / f"iter_{it}")
        seed = sc.seed + ROLLOUT_SEED + it
        # (1) the current generator's scenes, the current policy one step on.
        ep = ep0 if it == 0 else _episodes(sc, truth, net, splits, inputs)[0]
        nxt = next_step_snapshots(sc, snaps, ep.bank, ep.make_core, agent, seed, truth.signals)
        is_val = np.isin(nxt.run, splits["val"])
        train = nxt.take(np.flatnonzero(~is_val))
        val = nxt.take(np.flatnonzero(is_val)) if is_val.any() else train
        k_val = k_of(val, sc.generator.k_source)
        before = mean_reconstruction(net, road, val, k_val, seed + REC_SEED)
        # (2) the generator towards the hidden states the policy produced.
        net, log = train_section_generator(
            fixed,
            truth.section,
            train,
            val,
            progress,
            epochs=cfg.refine_epochs,
            init=net.state_dict(),
            extra=rec,
        )
        write_csv(log, folder / "generator_train_log.csv")
        # Each iteration's pair stays (iter_<i>/policy.pt beside it): any can be evaluated.
        save_section_generator(folder / "generator.pt", net, sc, {"refined_iterations": it + 1})
        after = mean_reconstruction(net, road, val, k_val, seed + REC_SEED)
        # (3) the policy on scenes the updated generator completes.
        ep, _ = _episodes(sc, truth, net, splits, inputs)
        res = train_policy(
            trained,
            ep.bank,
            folder,
            objective="mix",
            progress=progress,
            updates=cfg.refine_updates,
            init=agent.state_dict(),
            make_core=ep.make_core,
            val_runs=splits["val"],
            make_demand=ep.make_demand,
            prior_params=prior,
            recorded_pairs=pairs,
            driver_speed=ep.driver_speed,
        )
        agent = res["agent"]
        last = res["log"][-1]
        rows.append(
            {
                "iteration": it + 1,
                "next_step_scenes": len(nxt),
                "L_rec_before": before,
                "L_rec_after": after,
                "generator_epochs": len(log),
                "generator_val_loss": float(log["val_loss"].min()),
                "r_macro": last["r_macro"],
                "val_micro_logp": last["val_micro_logp"],
                "collisions": last["collisions"],
                "wall_s": round(time.perf_counter() - t0, 3),
            }
        )
        if progress:
            print(
                f"[refine] iteration {it + 1}/{cfg.refine_iterations}: L_rec {before:.4f} -> "
                f"{after:.4f} on {len(val)} validation scenes, r_macro {last['r_macro']:.4f}, "
                f"val micro logp {last['val_micro_logp']:.3f}"
            )
    save_section_generator(
        out / "generator.pt", net, sc, {"refined_iterations": cfg.refine_iterations}
    )
    last_policy = out / f"iter_{cfg.refine_iterations - 1}" / policy_file("mix")
    # The last fine-tune's checkpoint as written by PPO (none: the single pass's), copied
    # byte for byte: nothing to unpickle.
    with atomic_path(out / "policy.pt") as tmp:
        shutil.copyfile(last_policy if cfg.refine_iterations else policy, tmp)
    write_csv(pd.DataFrame(rows), out / "refine_log.csv")
    manifest = build_manifest(sc, command, stage="refine")  # type: ignore[arg-type]
    manifest.update(
        ground_truth=str(data),
        generator=str(generator),
        policy=str(policy),
        iterations=rows,
        timings_s={"refine": round(time.perf_counter() - t0, 3)},
        **extra_manifest,
    )
    write_stage_manifest(manifest, out, MANIFEST, FILES)
    return manifest

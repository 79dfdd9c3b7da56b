"""Stage I training and evaluation: fit G_phi on macro losses, check it on held-out runs.

``train_generator`` runs Algorithm 2 over minibatches of training snapshots (a fresh
random hidden set every epoch), stops early on the validation runs' loss, writes
``generator.pt`` atomically on every improvement, and logs ``generator_train_log.csv``.
``evaluate_generator`` completes held-out snapshots for each K with the generator and
the two baselines and writes ``generator_metrics.csv``.
"""

from __future__ import annotations

import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.checkpoints import load_network, save_network
from macromicro_sumo.data.ring import (
    GroundTruth,
    Snapshots,
    held_out_by_k,
    hide,
    load_ground_truth,
    snapshot_states,
    split_runs,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import (
    check_beside,
    prepare_out_dir,
    write_csv,
    write_stage_manifest,
)
from macromicro_sumo.generator.ring_gaps import PsiTensors
from macromicro_sumo.generator.ring_metrics import completion_metrics, summarise_metrics
from macromicro_sumo.generator.ring_model import (
    FEATURE_VERSION,
    GeneratorNet,
    macro_losses,
    reconstruction_loss,
    rollout,
    total_loss,
)
from macromicro_sumo.generator.ring_sampler import complete, complete_equal_gap, complete_uniform
from macromicro_sumo.generator.training import (
    GENERATOR_FILES,
    GENERATOR_MANIFEST,
    Batch,
    FitSettings,
    fit,
)
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.scenario.ring import Scenario

CHECKPOINT_FORMAT = "macromicro-generator"


def signature(sc: Scenario) -> dict[str, Any]:
    """What a generator depends on: a checkpoint is only valid for the same values."""
    return {
        "fleet.n_vehicles": sc.fleet.n_vehicles,
        "network.radius_m": sc.network.radius_m,
        "bounds.spacing_m": list(sc.bounds.spacing_m),
        "bounds.speed_mps": list(sc.bounds.speed_mps),
        "generator.psi_source": sc.generator.psi_source,
        "generator.bounds_source": sc.generator.bounds_source,
        "generator.spacing_dispersion": sc.generator.spacing_dispersion,
        "generator.gap_choice": sc.generator.gap_choice,
        "observation_layout": f"ring-gaps-v{FEATURE_VERSION}",
    }


def save_generator(
    path: Path, net: GeneratorNet, sc: Scenario, extra: dict[str, Any] | None = None
) -> None:
    save_network(path, CHECKPOINT_FORMAT, net, signature(sc), sc.to_dict(), extra)


def load_generator(path: Path | str, sc: Scenario) -> GeneratorNet:
    """Load ``generator.pt``; a corrupt file or one trained for another scenario is an error."""
    check_beside(path, GENERATOR_MANIFEST)
    return load_network(
        path,
        CHECKPOINT_FORMAT,
        "generator",
        signature(sc),
        lambda hidden_size: GeneratorNet(hidden_size, sc.generator.gap_choice),
        sc.source,
        before={"generator.gap_choice": "network"},  # the only choice before it was a key
    )


def _batch_loss(
    net: torch.nn.Module, snaps: Snapshots, sc: Scenario, gen: torch.Generator
) -> tuple[torch.Tensor, dict[str, float]]:
    arc, speed, generated, log_p = rollout(net, snaps, gen)
    psi = PsiTensors.of(snaps)
    terms = macro_losses(arc, speed, generated, psi, snaps.length_m)
    loss = total_loss(terms, sc.generator.lambda_v, sc.generator.lambda_d)
    if sc.generator.lambda_rec > 0:
        rec = reconstruction_loss(
            arc,
            speed,
            torch.as_tensor(snaps.arc_m, dtype=torch.float32),
            torch.as_tensor(snaps.speed_mps, dtype=torch.float32),
            generated,
            psi,
            snaps.length_m,
        )
        terms["L_rec"] = rec
        loss = loss + sc.generator.lambda_rec * rec
    # Score-function gradient for the discrete gap choices, batch-mean baseline.
    advantage = (loss - loss.mean()).detach()
    surrogate = loss.mean() + (advantage * log_p).mean()
    return surrogate, {k: float(v.detach().mean()) for k, v in terms.items()} | {
        "loss": float(loss.detach().mean())
    }


def train_generator(
    sc: Scenario,
    gt: GroundTruth,
    out: Path,
    progress: bool = True,
    *,
    given: tuple[Snapshots, Snapshots] | None = None,
    init: dict[str, Any] | None = None,
    epochs: int | None = None,
) -> dict[str, Any]:
    """Train on the train runs, early-stop on val runs; returns the split and timings.

    ``given`` = (train, val) snapshots with fixed hidden masks replaces the ground-truth
    snapshots with fresh random masks (the joint refinement trains on policy rollouts);
    ``init`` starts from existing weights.
    """
    cfg = sc.generator
    torch.manual_seed(sc.seed)
    splits = split_runs(gt.runs, cfg.held_out_fraction, sc.seed)
    rng = np.random.default_rng([sc.seed, 1])
    lo, hi = cfg.hidden_train
    if given is None:
        train = snapshot_states(gt, sc, splits["train"])
        val_states = snapshot_states(gt, sc, splits["val"]) if len(splits["val"]) else train
        val = hide(
            val_states,
            rng.integers(lo, hi + 1, len(val_states)),
            np.random.default_rng([sc.seed, 2]),
        )
    else:
        train, val = given
    net = GeneratorNet(cfg.hidden_size, cfg.gap_choice)
    if init is not None:
        net.load_state_dict(init)
    gen = torch.Generator().manual_seed(sc.seed)

    def epoch_batches(epoch: int) -> list[Batch]:
        snaps = hide(train, rng.integers(lo, hi + 1, len(train)), rng) if given is None else train
        perm = rng.permutation(len(snaps))
        return [
            (partial(_batch_loss, snaps=snaps.take(idx), sc=sc, gen=gen), len(idx))
            for idx in (perm[s : s + cfg.batch_size] for s in range(0, len(perm), cfg.batch_size))
        ]

    def validate(model: torch.nn.Module) -> dict[str, float]:
        with torch.no_grad():
            return _batch_loss(model, val, sc, torch.Generator().manual_seed(sc.seed + 17))[1]

    def save(model: torch.nn.Module, epoch: int, best: float) -> None:
        save_generator(out / "generator.pt", model, sc, {"epoch": epoch, "val_loss": best})

    t0 = time.perf_counter()
    settings = FitSettings(
        epochs or cfg.epochs, cfg.patience, cfg.lr, cfg.ema_decay, desc="train-generator"
    )
    log = fit(net, settings, epoch_batches, validate, save, progress)
    write_csv(log, out / "generator_train_log.csv")
    return {
        "splits": {k: v.tolist() for k, v in splits.items()},
        "train_s": time.perf_counter() - t0,
        "epochs": len(log),
        "best_val_loss": float(log["val_loss"].min()),
        "net": net,
    }


def held_out_sets(sc: Scenario, gt: GroundTruth) -> dict[int, Snapshots]:
    splits = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)
    states = snapshot_states(gt, sc, splits["held_out"])
    lo, hi = sc.generator.hidden_eval
    return held_out_by_k(states, range(lo, hi + 1), sc.seed)


def evaluate_generator(
    net: GeneratorNet, sc: Scenario, gt: GroundTruth
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(generator_metrics per method and K, per-snapshot metrics) on held-out runs."""
    per = []
    for k, snaps in held_out_sets(sc, gt).items():
        for method, fn in (
            ("generator", lambda s, seed: complete(net, s, sc.generator.t_max, seed)),
            ("uniform", complete_uniform),
            ("equal_gap", complete_equal_gap),
        ):
            m = completion_metrics(snaps, fn(snaps, sc.seed + k))
            m.insert(0, "method", method)
            per.append(m)
    per_df = pd.concat(per, ignore_index=True)
    return summarise_metrics(per_df), per_df


def completions_frame(
    snaps_by_k: dict[int, Snapshots], net: GeneratorNet, sc: Scenario
) -> pd.DataFrame:
    """completions.csv: every vehicle of every completed held-out snapshot, true state beside."""
    rows = []
    for k, snaps in snaps_by_k.items():
        comp = complete(net, snaps, sc.generator.t_max, sc.seed + k)
        b, n = snaps.arc_m.shape
        rows.append(
            pd.DataFrame(
                {
                    "K": k,
                    "snapshot": np.repeat(np.arange(b), n),
                    "run": np.repeat(snaps.run, n),
                    "time_s": np.repeat(snaps.time_s, n),
                    "slot": np.tile(np.arange(n), b),
                    "observed": (~snaps.hidden).ravel().astype(int),
                    "arc_pos_m": comp.arc_m.ravel(),
                    "theta_rad": (2 * np.pi * comp.arc_m / snaps.length_m).ravel(),
                    "speed_mps": comp.speed_mps.ravel(),
                    "true_arc_pos_m": snaps.arc_m.ravel(),
                    "true_speed_mps": snaps.speed_mps.ravel(),
                    "projected_in_snapshot": np.repeat(comp.projected, n),
                }
            )
        )
    return pd.concat(rows, ignore_index=True)


def check_psi(snaps: Snapshots, source: str) -> None:
    """Reject a Psi whose bounds no completion of N vehicles on the ring can satisfy."""
    n = snaps.arc_m.shape[1]
    d_min, d_max, v_min, v_max = snaps.psi[:, 2], snaps.psi[:, 3], snaps.psi[:, 4], snaps.psi[:, 5]
    bad = (
        (~np.isfinite(snaps.psi).all(axis=1))
        | (d_min > d_max)
        | (v_min > v_max)
        | (n * d_min > snaps.length_m)
        | (n * d_max < snaps.length_m)
    )
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise UserError(
            f"{source}: Psi of run {snaps.run[i]} at t = {snaps.time_s[i]:g} s has bounds d = [{d_min[i]:.2f}, "
            f"{d_max[i]:.2f}] m, v = [{v_min[i]:.2f}, {v_max[i]:.2f}] m/s that no completion of {n} vehicles "
            f"on a {snaps.length_m:.2f} m ring satisfies; accepted: d_min <= L/N <= d_max, v_min <= v_max"
        )


def run_train_generator(
    sc: Scenario, data: Path, out: Path, command: str = "", progress: bool = True
) -> dict[str, Any]:
    """CLI stage: train, evaluate on held-out runs, write generator.pt + metrics + log."""
    gt = load_ground_truth(data, sc)
    for snaps in held_out_sets(sc, gt).values():
        check_psi(snaps, str(Path(data) / "macro.csv"))
    out = prepare_out_dir(out)  # only once the inputs are known to be good
    torch.set_num_threads(1)  # a tiny MLP: one thread is fastest and leaves a core for SUMO
    res = train_generator(sc, gt, out, progress)
    summary, per = evaluate_generator(res.pop("net"), sc, gt)
    write_csv(summary, out / "generator_metrics.csv")
    write_csv(per, out / "generator_metrics_per_snapshot.csv")
    manifest = build_manifest(sc, command, stage="train-generator")
    manifest.update(
        ground_truth=str(data),
        splits=res["splits"],
        epochs=res["epochs"],
        best_val_loss=res["best_val_loss"],
        timings_s={"train_generator": round(res["train_s"], 3)},
    )
    write_stage_manifest(manifest, out, GENERATOR_MANIFEST, GENERATOR_FILES)
    return manifest


def run_complete(
    sc: Scenario, generator: Path, data: Path, out: Path, hidden: list[int] | None = None
) -> Path:
    """CLI stage: complete every held-out snapshot for each K; write completions.csv."""
    n = sc.fleet.n_vehicles
    ks = (
        hidden
        if hidden
        else list(range(sc.generator.hidden_eval[0], sc.generator.hidden_eval[1] + 1))
    )
    for k in ks:
        if not 0 <= k <= n:
            raise UserError(
                f"--hidden {k}: K must be in [0, {n}] (N = fleet.n_vehicles of {sc.source})"
            )
    net = load_generator(generator, sc)
    gt = load_ground_truth(data, sc)
    splits = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)
    states = snapshot_states(gt, sc, splits["held_out"])
    sets = held_out_by_k(states, ks, sc.seed)
    for snaps in sets.values():
        check_psi(snaps, str(Path(data) / "macro.csv"))
    out = prepare_out_dir(out)  # only once the inputs are known to be good
    write_csv(completions_frame(sets, net, sc), out / "completions.csv")
    return out / "completions.csv"

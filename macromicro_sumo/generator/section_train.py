"""Stage I on a road section: checkpoints and training (Algorithm 2).

``train_section_generator`` runs minibatches of training snapshots through the rollout
(``section_model``) with early stopping on the validation snapshots' loss. The CLI stage
(``train-generator``) that calls it: ``section_stage``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.checkpoints import load_network, save_network
from macromicro_sumo.data.objective import macro_loss
from macromicro_sumo.data.section import SectionSnapshots, draw_k, hidden_per_snapshot, hide_random
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import check_beside
from macromicro_sumo.generator.pair_dynamics import pair_term, recorded_pair_slope
from macromicro_sumo.generator.section_model import (
    FEATURE_VERSION,
    SectionGeneratorNet,
    section_losses,
)
from macromicro_sumo.generator.section_rollout import Scene, rollout
from macromicro_sumo.generator.section_sampler import k_of, one_thread
from macromicro_sumo.generator.section_scene import Psi, Road
from macromicro_sumo.generator.section_spread import (
    pooled_dispersion,
    spacing_variance,
    speed_spread_target,
)
from macromicro_sumo.generator.training import (
    GENERATOR_MANIFEST,
    Batch,
    FitSettings,
    fit,
)
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionGeneratorConfig, SectionScenario

CHECKPOINT_FORMAT = "macromicro-section-generator"
EVAL_BATCH = 256  # snapshots per forward pass in validation and metrics

# A term added to the loss: its name, weight and per-scene values (B,) on a batch's
# completed scenes (joint refinement's lambda_rec L_rec: generator/reconstruction.py).
ExtraTerm = tuple[str, float, Callable[[Scene, SectionSnapshots, Road], torch.Tensor]]


# --------------------------------------------------------------------------- checkpoints


def signature(sc: SectionScenario) -> dict[str, Any]:
    """What a section generator depends on: a checkpoint is only valid for the same values."""
    return {
        "section.edges": list(sc.section.edges),
        "section.closed": bool(sc.section.closed),
        "simulation.step_length_s": float(sc.simulation.step_length_s),
        "generator.gap_choice": sc.generator.gap_choice,
        "generator.dispersion_feature": bool(sc.generator.dispersion_feature),
        "generator.hidden_layers": int(sc.generator.hidden_layers),
        "observation_layout": f"section-gaps-v{FEATURE_VERSION}",
    }


def save_section_generator(
    path: Path, net: SectionGeneratorNet, sc: SectionScenario, extra: dict[str, Any] | None = None
) -> None:
    """Write ``generator.pt`` atomically (a crash never leaves a half-written checkpoint)."""
    save_network(path, CHECKPOINT_FORMAT, net, signature(sc), sc.to_dict(), extra)


def load_section_generator(path: Path | str, sc: SectionScenario) -> SectionGeneratorNet:
    """Load a section ``generator.pt``; a corrupt file or one trained for another section is
    a one-line UserError naming the file and what differs."""
    check_beside(path, GENERATOR_MANIFEST)
    return load_network(
        path,
        CHECKPOINT_FORMAT,
        "section generator",
        signature(sc),
        lambda hidden_size: SectionGeneratorNet(
            hidden_size,
            sc.generator.gap_choice,
            sc.generator.dispersion_feature,
            sc.generator.hidden_layers,
        ),
        sc.source or sc.name,
        # the only values before they were keys
        before={
            "generator.gap_choice": "network",
            "generator.dispersion_feature": False,
            "generator.hidden_layers": 1,
        },
    )


def check_gap_choice(sc: SectionScenario, section: Section) -> None:
    """``generator.gap_choice = "posterior"`` is the ring's: a closed one-lane section, the
    measured dispersion (its spacing std is the posterior's). A one-line UserError else."""
    cfg = sc.generator
    if cfg.gap_choice != "posterior":
        return
    where = f'{sc.source or sc.name}: generator.gap_choice = "posterior"'
    if not section.closed or section.max_lanes != 1:
        raise UserError(
            f"{where} needs a closed one-lane section (this one: closed = {section.closed}, "
            f'{section.max_lanes} lanes); accepted "network" here'
        )
    if cfg.spacing_dispersion != "measured":
        raise UserError(
            f"{where} needs the detectors' spacing std: generator.spacing_dispersion = "
            f'"{cfg.spacing_dispersion}"; accepted "measured"'
        )


# --------------------------------------------------------------------------- training


def squared_dispersion(l_var: torch.Tensor, psi: Psi) -> torch.Tensor:
    """``generator.dispersion_error = "squared"``: the measured L_var |X - sigma^2| / d^2 of
    each scene (X its spacing variance, sigma psi's spacing std, d psi's mean spacing) as
    (X - sigma^2)^2 / (d^2 sigma^2); L_var squared where psi has no spacing std.

    Why: the absolute error makes the scenes' median X meet sigma^2 and their right-skewed
    X then averages above it (ring as a section, K = 2..4: mean X 1.09-1.16 sigma^2, the
    truth's 0.97 sigma^2; spacing std +3.5..+5.5%); the squared error matches the mean."""
    known = psi.d_std_known & (psi.d_std > 0)
    ratio = torch.where(known, psi.d_mean / psi.d_std.clamp(min=1e-9), 1.0) ** 2
    return l_var**2 * ratio


def _batch_loss(
    net: SectionGeneratorNet,
    road: Road,
    snaps: SectionSnapshots,
    k: np.ndarray,
    cfg: SectionGeneratorConfig,
    gen: torch.Generator,
    extra: ExtraTerm | None = None,
    pair_target: float = math.nan,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Surrogate loss of one batch (reparameterised terms + score-function term for the gap
    choices, batch-mean baseline) and the batch means of every term. ``pair_target``: the
    recorded pairs' slope L_pair scores against (``generator.lambda_pair``)."""
    scene, log_p = rollout(net, road, snaps, k, gen)
    psi = Psi.of(snaps.psi, speed_spread_target(snaps))
    terms = section_losses(
        scene.lane,
        scene.arc,
        scene.speed,
        scene.present,
        psi,
        road,
        cfg.spacing_dispersion,
        cfg.dispersion_center,
        scene.n_obs_slots if cfg.spacing_set == "touched" else None,
    )
    if cfg.dispersion_error == "squared":
        terms["L_var"] = squared_dispersion(terms["L_var"], psi)
    if cfg.dispersion_pool > 0:
        x = spacing_variance(
            scene.lane,
            scene.arc,
            scene.present,
            psi,
            road,
            cfg.dispersion_center,
            scene.n_obs_slots if cfg.spacing_set == "touched" else None,
        )
        pooled = pooled_dispersion(x, psi, scene.k)
        terms["L_var"] = terms["L_var"] + cfg.dispersion_pool * pooled
    loss = macro_loss(terms, cfg.lambda_v, cfg.lambda_d)
    if extra is not None:
        name, weight, term = extra
        terms[name] = term(scene, snaps, road)
        loss = loss + weight * terms[name]
    advantage = (loss - loss.mean()).detach()
    surrogate = loss.mean() + (advantage * log_p).mean()
    if cfg.lambda_pair > 0:
        # A batch-level term on the speeds alone: moving the vehicles in their gaps for it
        # undid the spacing spread (ring: L_var x 6 at the same weight).
        l_pair = pair_term(
            scene.lane,
            scene.arc.detach(),
            scene.speed,
            scene.present,
            scene.k,
            road,
            scene.n_obs_slots,
            pair_target,
            psi.v_std,
        )
        surrogate = surrogate + cfg.lambda_pair * l_pair
        loss = loss + cfg.lambda_pair * l_pair.detach()
        terms["L_pair"] = l_pair.expand(len(loss))
    if not surrogate.requires_grad:  # nothing generated (K = 0 throughout): a zero step
        surrogate = surrogate + sum(p.sum() for p in net.parameters()) * 0.0
    stats = {name: float(v.detach().mean()) for name, v in terms.items()}
    return surrogate, stats | {"loss": float(loss.detach().mean())}


def _eval_loss(
    net: SectionGeneratorNet,
    road: Road,
    snaps: SectionSnapshots,
    k: np.ndarray,
    cfg: SectionGeneratorConfig,
    seed: int,
    extra: ExtraTerm | None = None,
    pair_target: float = math.nan,
) -> dict[str, float]:
    """Mean of every term over ``snaps`` with a fixed seed (validation: comparable epochs)."""
    gen = torch.Generator().manual_seed(seed)
    sums: dict[str, float] = {}
    with torch.no_grad():
        for s in range(0, len(snaps), EVAL_BATCH):
            idx = np.arange(s, min(s + EVAL_BATCH, len(snaps)))
            _, st = _batch_loss(net, road, snaps.take(idx), k[idx], cfg, gen, extra, pair_target)
            for name, v in st.items():
                sums[name] = sums.get(name, 0.0) + v * len(idx)
    return {name: v / max(len(snaps), 1) for name, v in sums.items()}


def train_section_generator(
    sc: SectionScenario,
    section: Section,
    train: SectionSnapshots,
    val: SectionSnapshots,
    progress: bool = True,
    *,
    out: Path | None = None,
    epochs: int | None = None,
    init: dict[str, Any] | None = None,
    extra: ExtraTerm | None = None,
) -> tuple[SectionGeneratorNet, pd.DataFrame]:
    """Algorithm 2 on a section: minibatches of training snapshots, early stopping on the
    validation snapshots' loss. Returns the best network and the per-epoch log.

    ``out``: write ``generator.pt`` there (atomically) on every improvement, so an
    interrupted run keeps its best weights. ``epochs`` overrides ``sc.generator.epochs``.
    ``init``: start from these weights (a fine-tune); ``extra``: a term added to the loss
    of every batch and of validation (joint refinement's L_rec).
    """
    check_gap_choice(sc, section)
    with one_thread():
        return _train(sc, section, train, val, progress, out, epochs, init, extra)


def _train(
    sc: SectionScenario,
    section: Section,
    train: SectionSnapshots,
    val: SectionSnapshots,
    progress: bool,
    out: Path | None,
    epochs: int | None,
    init: dict[str, Any] | None = None,
    extra: ExtraTerm | None = None,
) -> tuple[SectionGeneratorNet, pd.DataFrame]:
    cfg = sc.generator
    torch.manual_seed(sc.seed)
    # Trained on SUMO's lane indices, completing along the connections (complete_section):
    # trained along them, netgen_corridor's generator did worse (Stage II speed error,
    # policy / idm_calibrated 0.89 / 1.04 m/s; 3e1f4d0's, completing so: 0.08 / 0.12).
    road = Road.of(section, connections=False)
    net = SectionGeneratorNet(
        cfg.hidden_size, cfg.gap_choice, cfg.dispersion_feature, cfg.hidden_layers
    )
    if init is not None:
        net.load_state_dict(init)
    gen = torch.Generator().manual_seed(sc.seed)
    rng = np.random.default_rng([sc.seed, 31])
    k_train, k_val = k_of(train, cfg.k_source), k_of(val, cfg.k_source)
    pair_target = math.nan
    if cfg.lambda_pair > 0:
        # The micro data: every recorded vehicle where each snapshot hides its own K (the
        # ring), else the instrumented ones.
        rec = train.valid if hidden_per_snapshot(sc) else train.valid & train.observed
        pair_target = recorded_pair_slope(train, rec, road)

    def epoch_batches(epoch: int) -> list[Batch]:
        snaps, k = train, k_train
        if hidden_per_snapshot(sc):  # fresh hidden sets every epoch, as the ring's training
            snaps = hide_random(train, draw_k(train, cfg.hidden_train, rng), rng)
            k = k_of(snaps, cfg.k_source)
        perm = rng.permutation(len(snaps))
        return [
            (
                partial(
                    _batch_loss,
                    road=road,
                    snaps=snaps.take(idx),
                    k=k[idx],
                    cfg=cfg,
                    gen=gen,
                    extra=extra,
                    pair_target=pair_target,
                ),
                len(idx),
            )
            for idx in (perm[s : s + cfg.batch_size] for s in range(0, len(perm), cfg.batch_size))
        ]

    def validate(model: torch.nn.Module) -> dict[str, float]:
        return _eval_loss(model, road, val, k_val, cfg, sc.seed + 17, extra, pair_target)

    def save(model: torch.nn.Module, epoch: int, best: float) -> None:
        save_section_generator(
            Path(out) / "generator.pt", model, sc, {"epoch": epoch, "val_loss": best}
        )

    settings = FitSettings(
        epochs or cfg.epochs,
        cfg.patience,
        cfg.lr,
        cfg.ema_decay,
        "train-section-generator",
        cfg.ema_warmup,
        cfg.min_epochs,
    )
    log = fit(net, settings, epoch_batches, validate, save if out is not None else None, progress)
    return net, log

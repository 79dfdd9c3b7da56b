"""Algorithm 2's training loop, one for every road (the ring and any section).

The road's own code says what a batch is (``Batch``: the surrogate loss of a minibatch and
its terms) and how the validation snapshots are scored; ``fit`` does the rest: clipped Adam
steps, an optional exponential moving average of the weights, early stopping on the
validation loss, and the best weights handed to ``save`` on every improvement (so an
interrupted run keeps them). The log has one row per epoch: ``train_<term>`` (mean over the
epoch's snapshots) and ``val_<term>``.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import pandas as pd
import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from macromicro_sumo.progress import tqdm

# A minibatch: given the network, its surrogate loss (to minimise) and the batch means of
# the loss terms, named; and how many snapshots it holds (the epoch's means weigh by it).
Batch = tuple[Callable[[nn.Module], tuple[torch.Tensor, dict[str, float]]], int]

# What a generator stage writes beside its manifest (ring and sections alike).
GENERATOR_FILES = (
    "generator.pt",
    "generator_train_log.csv",
    "generator_metrics.csv",
    "generator_metrics_per_snapshot.csv",
)
GENERATOR_MANIFEST = "generator_manifest.json"

GRAD_CLIP = 5.0  # global norm: the score-function gradient of the gap choice has outliers
# A validation loss must fall by more than this to count as an improvement: EMA weights
# move slowly, and improvements in the 7th digit are noise that only delays stopping.
MIN_DELTA = 1e-6


@dataclass(frozen=True)
class FitSettings:
    """How long and how fast ``fit`` trains (the ``[generator]`` table's values)."""

    epochs: int
    patience: int  # epochs without improvement before stopping
    lr: float
    ema_decay: float = 0.0  # 0: validate and keep the raw weights
    desc: str = "train-generator"  # the progress line's label
    # The average's decay ramps up as min(ema_decay, (1 + n) / (10 + n)) after n updates,
    # so that the early average does not hold on to the initial weights (``ema_fn``).
    ema_warmup: bool = False
    min_epochs: int = 0  # no early stop before this many epochs


def ema_fn(decay: float, warmup: bool) -> Callable[..., torch.Tensor]:
    """The moving average's update of one parameter tensor (``AveragedModel``'s avg_fn).

    Without warm-up the average keeps decay^n of the initial weights after n updates
    (0.995: 38% after 200 batches): interpolated with the trained ones they validate
    worse than either, and early stopping ended trainings on that plateau (ring as a
    section: 52-181 epochs, spacing std off by up to 16%). With it the initial weights'
    share is 9 / (9 + n)-ish and the long average only builds up once training settles."""

    def update(avg: torch.Tensor, new: torch.Tensor, n: torch.Tensor | int) -> torch.Tensor:
        d = min(decay, (1.0 + float(n)) / (10.0 + float(n))) if warmup else decay
        return d * avg + (1.0 - d) * new

    return update


def fit(
    net: nn.Module,
    settings: FitSettings,
    epoch_batches: Callable[[int], Sequence[Batch]],
    validate: Callable[[nn.Module], dict[str, float]],
    save: Callable[[nn.Module, int, float], None] | None = None,
    progress: bool = True,
) -> pd.DataFrame:
    """Train ``net`` in place; it ends with the best validated weights, in eval mode.

    ``epoch_batches(epoch)`` gives the epoch's minibatches (built lazily by the caller, so
    its random draws keep their order); ``validate(model)`` returns the validation terms
    with ``"loss"`` among them; ``save(model, epoch, best_loss)`` is called on every
    improvement. Returns the per-epoch log.
    """
    opt = torch.optim.Adam(net.parameters(), lr=settings.lr)
    # The REINFORCE gradient of the gap choice is noisy: averaged weights change less with
    # the training seed than the last step's (ema_decay > 0 validates and keeps them).
    ema = None
    if settings.ema_decay > 0 and settings.ema_warmup:
        ema = AveragedModel(net, avg_fn=ema_fn(settings.ema_decay, True))
    elif settings.ema_decay > 0:
        ema = AveragedModel(net, multi_avg_fn=get_ema_multi_avg_fn(settings.ema_decay))
    kept = ema.module if ema is not None else net
    best, best_state, bad, log = math.inf, copy.deepcopy(net.state_dict()), 0, []
    t0 = time.perf_counter()
    bar = tqdm(range(settings.epochs), desc=settings.desc, unit="epoch", disable=not progress)
    for epoch in bar:
        net.train()
        sums: dict[str, float] = {}
        seen = 0
        for batch, n in epoch_batches(epoch):
            loss, terms = batch(net)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), GRAD_CLIP)
            opt.step()
            if ema is not None:
                ema.update_parameters(net)
            for name, v in terms.items():
                sums[name] = sums.get(name, 0.0) + v * n
            seen += n
        kept.eval()
        vs = validate(kept)
        log.append(
            {
                "epoch": epoch,
                "wall_s": time.perf_counter() - t0,
                **{f"train_{k}": v / max(seen, 1) for k, v in sums.items()},
                **{f"val_{k}": v for k, v in vs.items()},
            }
        )
        if vs["loss"] < best - MIN_DELTA:
            best, best_state, bad = vs["loss"], copy.deepcopy(kept.state_dict()), 0
            if save is not None:
                save(kept, epoch, best)
        else:
            bad += 1
        bar.set_postfix(
            train=f"{sums.get('loss', math.nan) / max(seen, 1):.4f}",
            val=f"{vs['loss']:.4f}",
            best=f"{best:.4f}",
        )
        if bad >= settings.patience and epoch + 1 >= settings.min_epochs:
            break
    net.load_state_dict(best_state)
    net.eval()
    return pd.DataFrame(log)

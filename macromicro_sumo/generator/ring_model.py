"""Stage I on the ring: the hidden-vehicle generator G_phi (paper: Algorithm 2).

For every gap of the current scene (``ring_gaps``) an MLP, given the gap's features and
the macro descriptor Psi, outputs:

* a score: which gap receives the next vehicle (categorical over the current gaps);
* where in the gap: a logit-normal fraction of the gap (reparameterised);
* its speed: logit-normal on Psi's [v_min, v_max] (reparameterised, always in bounds).

Training minimises L_gen = lambda_v L_speed + lambda_d (L_mean + L_min + L_max + L_var)
(+ lambda_rec L_rec as a switch). Gradients reach the positions and speeds through the
reparameterised samples; the discrete gap choice gets the score-function (REINFORCE)
gradient of the same loss with a batch-mean baseline, which is the unbiased estimator
for a discrete choice inside a stochastic computation graph. This module holds the
features, the network, the proposal, the losses and the training rollout; training
itself is ``ring_train``, inference (Algorithm 3) ``ring_sampler``.

Inference runs in numpy (float64 geometry, the MLP in float32 with the trained weights,
``GeneratorNet.forward_numpy``): placing one vehicle of one snapshot takes a few hundred
tiny array operations, and numpy's per-operation overhead is a third of torch's. The
features are one definition for both (``ring_gaps.array_module``); training runs them in
torch, with gradients, exactly as before (same autograd graph, bit-identical weights).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import nn

from macromicro_sumo.data.objective import MacroTarget, macro_loss, macro_terms
from macromicro_sumo.data.ring import Snapshots
from macromicro_sumo.generator.ring_gaps import (
    PsiTensors,
    array_module,
    clip,
    ring_gaps,
    scene_gaps,
    stack_last,
    take,
)
from macromicro_sumo.generator.ring_posterior import gap_posterior

FEATURE_VERSION = 2
N_GAP_FEATURES = 7
N_GLOBAL_FEATURES = 9
LOSS_TERMS = ("L_speed", "L_mean", "L_min", "L_max", "L_var")
# Limits of the log-std of the position and speed heads.
FRAC_LOG_STD = (-5.0, 2.0)
SPEED_LOG_STD = (-6.0, 1.0)


# --------------------------------------------------------------------------- features


def features(
    arc: Any,
    speed: Any,
    present: Any,
    remaining: Any,
    psi: PsiTensors,
    length_m: float,
    geometry: tuple[Any, ...],
) -> tuple[Any, ...]:
    """Per-gap and global features of the current scene (all relative, no labels).

    ``geometry`` is ``scene_gaps``' result (same backend as ``arc``). Returns (gap features
    (B, N, 7), global features (B, 9), the mean speed the vehicles still to place need (B,)).
    """
    xp = array_module(arc)
    n = arc.shape[1]
    m = present.sum(1)
    empty = m == 0
    follower, leader, gap, _, _ = geometry
    vs, vm, dm, d_min, d_max = psi.columns
    # Speeds enter the features detached: otherwise training uses a generated vehicle's
    # speed as a side channel to steer later placements (L_dist), pulling speeds away from
    # Psi's mean. A speed reaches the loss only through L_speed (and the speed centring).
    speed_in = speed.detach() if hasattr(speed, "detach") else speed
    v_f = xp.where(empty[:, None], vm, take(speed_in, follower))
    v_l = xp.where(empty[:, None], vm, take(speed_in, leader))
    gap_dm = gap / dm
    gap_feat = stack_last(
        [
            gap_dm,
            (gap - d_min) / dm,
            (gap - d_max) / dm,
            gap_dm - 1.0 - remaining[:, None] / n,
            (v_f - vm) / vs,
            (v_l - vm) / vs,
            gap / length_m,
        ]
    )
    v_sum = (speed * present).sum(1)
    v_sum_in = (speed_in * present).sum(1)
    # The mean speed the vehicles still to place need for the fleet to average Psi's mean.
    need_v = (n * psi.v_mean - v_sum) / clip(remaining, 1)
    need_in = (n * psi.v_mean - v_sum_in) / clip(remaining, 1)
    mean_v = xp.where(empty, psi.v_mean, v_sum_in / clip(m, 1))
    d_min_rel, d_max_rel, *v_static = psi.static_features
    glob = stack_last(
        [
            remaining / n,
            m / n,
            d_min_rel,
            d_max_rel,
            (need_in - psi.v_mean) / psi.v_scale,
            (mean_v - psi.v_mean) / psi.v_scale,
            *v_static,
        ]
    )
    return gap_feat, glob, need_v


@dataclass
class Observation:
    """What one autoregressive step sees (torch or numpy, as its inputs)."""

    geometry: tuple[Any, ...]  # scene_gaps
    gap_feat: Any  # (B, N, N_GAP_FEATURES)
    glob: Any  # (B, N_GLOBAL_FEATURES)
    need_v: Any  # (B,)


def observe(
    arc: Any,
    speed: Any,
    present: Any,
    remaining: Any,
    psi: PsiTensors,
    length_m: float,
    anchor: Any,
) -> Observation:
    """Geometry and features of a scene; ``remaining`` counts the vehicles still to place,
    the next one included, and ``anchor`` places the first vehicle of an empty ring."""
    geometry = scene_gaps(arc, present, length_m, anchor)
    return Observation(geometry, *features(arc, speed, present, remaining, psi, length_m, geometry))


# --------------------------------------------------------------------------- model


class GeneratorNet(nn.Module):
    """Shared MLP scoring every gap: (logit, fraction mean, fraction log-std, speed mean, speed log-std).

    ``gap_choice`` is how a rollout picks the gap of the next vehicle: "network" draws it
    from the logits (the paper), "posterior" from ``gap_posterior`` (the logits are then
    unused and the network learns where in the gap and how fast).
    """

    def __init__(self, hidden_size: int = 64, gap_choice: str = "network") -> None:
        super().__init__()
        self.hidden_size = hidden_size
        self.gap_choice = gap_choice
        self.body = nn.Sequential(
            nn.Linear(N_GAP_FEATURES + N_GLOBAL_FEATURES, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, 5),
        )

    def forward(self, gap_feat: torch.Tensor, glob: torch.Tensor) -> torch.Tensor:
        x = torch.cat([gap_feat, glob[:, None, :].expand(-1, gap_feat.shape[1], -1)], dim=-1)
        return self.body(x)

    def numpy_weights(self) -> tuple[np.ndarray, ...]:
        """The layers as numpy views of the parameters (no copy, so in-place updates show):
        (W1 for the gap features, W1 for the global ones, b1, W2, b2, W3, b3), transposed."""
        params = tuple(self.body.parameters())
        cached = _NUMPY_WEIGHTS.get(self)
        if cached is None or any(a is not b for a, b in zip(cached[0], params, strict=True)):
            w1, b1, w2, b2, w3, b3 = (p.detach().numpy() for p in params)
            f = N_GAP_FEATURES
            cached = params, (w1[:, :f].T, w1[:, f:].T, b1, w2.T, b2, w3.T, b3)
            _NUMPY_WEIGHTS[self] = cached
        return cached[1]

    def forward_numpy(
        self, gap_feat: np.ndarray, glob: np.ndarray, weights: tuple[np.ndarray, ...] | None = None
    ) -> np.ndarray:
        """``forward`` in float32 numpy (inference): the global features enter the first
        layer once per scene instead of once per gap."""
        w1g, w1s, b1, w2, b2, w3, b3 = weights or self.numpy_weights()
        x, g = gap_feat.astype(np.float32), glob.astype(np.float32)
        h = np.tanh(x @ w1g + (g @ w1s + b1)[:, None, :])
        return np.tanh(h @ w2 + b2) @ w3 + b3


# Numpy views of a network's layers, kept beside it (not in it: a deep copy must not
# carry views of the original's memory).
_NUMPY_WEIGHTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def speed_base(need_v: Any, psi: PsiTensors) -> Any:
    """Logit of the speed the remaining vehicles need, on Psi's [v_min, v_max].

    Speeds live in Psi's [v_min, v_max] by construction (logit-normal on that interval):
    the paper's loss has no speed-bound term, so an unbounded proposal drifts outside.
    Centred on the speed the remaining vehicles need for Psi's mean: the MLP adds a residual.
    """
    need = clip((need_v - psi.v_min) / clip(psi.v_range, 1e-3), 0.02, 0.98)
    return torch.logit(need) if isinstance(need, torch.Tensor) else np.log(need / (1 - need))


@dataclass
class Proposal:
    """S candidates for each of B scenes: (S, B) tensors."""

    gap_pos: torch.Tensor
    arc: torch.Tensor
    speed: torch.Tensor
    frac: torch.Tensor
    gap: torch.Tensor
    log_prob_choice: torch.Tensor


def propose(
    net: GeneratorNet,
    obs: Observation,
    psi: PsiTensors,
    length_m: float,
    n_samples: int,
    gen: torch.Generator,
    allowed: torch.Tensor | None = None,
    choice_logits: torch.Tensor | None = None,
) -> Proposal:
    """Sample ``n_samples`` candidates for the next hidden vehicle of every scene (torch,
    reparameterised: the training rollout). ``allowed`` (B, N) optionally removes gap
    choices (in arc order) before sampling; ``choice_logits`` (B, N) replace the network's
    gap scores (``gap_choice = "posterior"``)."""
    _, _, gap, valid, start = obs.geometry
    b = gap.shape[0]
    out = net(obs.gap_feat.float(), obs.glob.float())
    if allowed is not None:
        valid = valid & (allowed | ~(allowed & valid).any(dim=1, keepdim=True))
    scores = out[..., 0] if choice_logits is None else choice_logits.to(out.dtype)
    logits = scores.masked_fill(~valid, -torch.inf)
    probs = torch.softmax(logits, dim=1)
    choice = torch.multinomial(probs, n_samples, replacement=True, generator=gen)  # (B, S)
    log_p = torch.log_softmax(logits, dim=1)
    pick = out.gather(1, choice[..., None].expand(-1, -1, out.shape[-1])).transpose(0, 1)
    eps = torch.randn(n_samples, b, 2, generator=gen)
    frac = torch.sigmoid(pick[..., 1] + torch.exp(pick[..., 2].clamp(*FRAC_LOG_STD)) * eps[..., 0])
    frac = frac.clamp(1e-3, 1 - 1e-3)
    base = speed_base(obs.need_v, psi)
    u = torch.sigmoid(
        base + pick[..., 3] + torch.exp(pick[..., 4].clamp(*SPEED_LOG_STD)) * eps[..., 1]
    )
    v = psi.v_min + psi.v_range * u
    g = gap.gather(1, choice).T
    new_arc = torch.remainder(start.gather(1, choice).T + frac * g, length_m)
    return Proposal(choice.T, new_arc, v, frac, g, log_p.gather(1, choice).T)


# --------------------------------------------------------------------------- losses


def macro_losses(
    arc: torch.Tensor,
    speed: torch.Tensor,
    generated: torch.Tensor,
    psi: PsiTensors,
    length_m: float,
) -> dict[str, torch.Tensor]:
    """The macro terms of completed scenes, (B,) each (``data.objective``).

    A (the gaps influenced by generated vehicles) holds every gap whose follower or
    leader was generated. When Psi carries the detectors' spacing std ``d_std``, L_var is
    the measured dispersion: the paper's std(d_A) / d_mean pulls every completion towards
    equal gaps, which the measured spacing distribution contradicts.
    """
    present = torch.ones_like(generated)
    follower, leader, gap, _ = ring_gaps(arc, present, length_m)
    a = (generated.gather(1, follower) | generated.gather(1, leader)).float()
    target = MacroTarget(
        psi.v_mean,
        psi.d_mean,
        psi.d_min,
        psi.d_max,
        spacing_std_m=None if psi.d_std is None else torch.as_tensor(psi.d_std),
    )
    # eps: sqrt has an infinite slope at 0; the epsilon keeps equal gaps trainable.
    return macro_terms(speed, None, gap, a, target, eps=1e-8)


def total_loss(terms: dict[str, torch.Tensor], lambda_v: float, lambda_d: float) -> torch.Tensor:
    return macro_loss(terms, lambda_v, lambda_d)


def reconstruction_loss(
    arc: torch.Tensor,
    speed: torch.Tensor,
    true_arc: torch.Tensor,
    true_speed: torch.Tensor,
    hidden: torch.Tensor,
    psi: PsiTensors,
    length_m: float,
) -> torch.Tensor:
    """L_rec = mean over hidden of ||s_hat - s||^2 (angle in rad, speed / v_scale), matched.

    Generated vehicles are matched to true hidden ones by the assignment minimising the
    total error (vehicles are unlabelled), computed on detached values.
    """
    b, n = arc.shape
    th = 2 * math.pi / length_m
    loss = arc.new_zeros(b)
    with torch.no_grad():
        perms = []
        for i in range(b):
            idx = torch.nonzero(hidden[i]).flatten()
            if len(idx) == 0:
                perms.append((idx, idx))
                continue
            da = (
                torch.remainder(
                    arc[i, idx][:, None] - true_arc[i, idx][None, :] + length_m / 2, length_m
                )
                - length_m / 2
            )
            dv = (speed[i, idx][:, None] - true_speed[i, idx][None, :]) / psi.v_scale[i]
            r, c = linear_sum_assignment(((da * th) ** 2 + dv**2).numpy())
            perms.append((idx[r], idx[c]))
    for i, (gi, ti) in enumerate(perms):
        if len(gi) == 0:
            continue
        da = torch.remainder(arc[i, gi] - true_arc[i, ti] + length_m / 2, length_m) - length_m / 2
        dv = (speed[i, gi] - true_speed[i, ti]) / psi.v_scale[i]
        loss[i] = ((da * th) ** 2 + dv**2).mean()
    return loss


# --------------------------------------------------------------------------- rollouts


def _next_hidden_slot(hidden: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    free = hidden & ~present
    return torch.where(
        free.any(dim=1), free.float().argmax(dim=1), torch.zeros(free.shape[0], dtype=torch.long)
    )


def rollout(net: GeneratorNet, snaps: Snapshots, gen: torch.Generator) -> tuple[torch.Tensor, ...]:
    """Training rollout (no rejection): returns (arc, speed, generated mask, sum log p(choice))."""
    hidden = torch.as_tensor(snaps.hidden)
    present = ~hidden
    arc = torch.as_tensor(snaps.arc_m, dtype=torch.float32).masked_fill(hidden, 0.0)
    speed = torch.as_tensor(snaps.speed_mps, dtype=torch.float32).masked_fill(hidden, 0.0)
    psi = PsiTensors.of(snaps)
    psi_np = PsiTensors.arrays(snaps) if net.gap_choice == "posterior" else None
    b, n = arc.shape
    log_p = arc.new_zeros(b)
    k = hidden.sum(dim=1)
    for step in range(int(k.max().item()) if b else 0):
        active = k > step
        remaining = (k - step).clamp(min=0)
        anchor = torch.rand(b, generator=gen) * snaps.length_m
        obs = observe(arc, speed, present, remaining, psi, snaps.length_m, anchor)
        choice_logits = None
        if net.gap_choice == "posterior":
            _, _, gap, valid, _ = obs.geometry
            choice_logits = torch.as_tensor(
                gap_posterior(gap.detach().numpy(), valid.numpy(), remaining.numpy(), psi_np)
            )
        prop = propose(net, obs, psi, snaps.length_m, 1, gen, choice_logits=choice_logits)
        slot = _next_hidden_slot(hidden, present)
        onehot = torch.nn.functional.one_hot(slot, n).bool() & active[:, None]
        arc = torch.where(onehot, prop.arc[0][:, None], arc)
        speed = torch.where(onehot, prop.speed[0][:, None], speed)
        present = present | onehot
        log_p = log_p + torch.where(active, prop.log_prob_choice[0], torch.zeros_like(log_p))
    return arc, speed, hidden, log_p

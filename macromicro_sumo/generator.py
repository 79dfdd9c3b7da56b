"""Stage I: the hidden-vehicle generator G_phi (paper: Algorithms 2 and 3).

The scene is a set of vehicles on the ring. Each autoregressive step looks at the gaps of
the current scene (observed vehicles plus those generated so far), sorted by angle, so
the model does not depend on the order or labels of vehicles and the ring has no start.
For every gap an MLP, given the gap's features and the macro descriptor Psi, outputs:

* a score: which gap receives the next vehicle (categorical over the current gaps);
* where in the gap: a logit-normal fraction of the gap (reparameterised);
* its speed: logit-normal on Psi's [v_min, v_max] (reparameterised, always in bounds).

With no vehicle present (K = N) the first vehicle goes anywhere (rotation symmetry):
its gap is the whole ring from a random angle.

Training minimises L_gen = lambda_v L_speed + lambda_d (L_mean + L_min + L_max + L_var)
(+ lambda_rec L_rec as a switch). Gradients reach the positions and speeds through the
reparameterised samples; the discrete gap choice gets the score-function (REINFORCE)
gradient of the same loss with a batch-mean baseline, which is the unbiased estimator
for a discrete choice inside a stochastic computation graph.

Inference is Algorithm 3, batched over snapshots: every step proposes T_max candidates at
once (the proposal distribution does not change between trials, so this equals
resampling one at a time) and keeps the first whose touched gaps and speed are within
bounds; if none is, the last candidate is projected onto the nearest feasible point and
counted. A touched gap that will still receive vehicles is judged by what it can hold:
it must split into m + 1 gaps in [d_min, d_max] for some m <= vehicles still to place
(the paper's check when none remain; without it a whole scene, K = N, could never start).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pandas as pd
import torch
from scipy.optimize import linear_sum_assignment
from torch import nn

from macromicro_sumo.dataset import Snapshots

FEATURE_VERSION = 2
N_GAP_FEATURES = 7
N_GLOBAL_FEATURES = 9
LOSS_TERMS = ("L_speed", "L_mean", "L_min", "L_max", "L_var")


# --------------------------------------------------------------------------- scene geometry


def ring_gaps(
    arc: torch.Tensor, present: torch.Tensor, length_m: float
) -> tuple[torch.Tensor, ...]:
    """Gaps of the present vehicles in arc order, batched over rows.

    Returns (follower slot, leader slot, gap [m], valid) each (B, N): position i holds
    the i-th gap in arc order; positions >= the number of present vehicles are invalid.
    A lone vehicle's gap is the whole ring.
    """
    n = arc.shape[1]
    order = torch.where(present, arc, arc + 4 * length_m).argsort(dim=1)
    m = present.sum(dim=1, keepdim=True)
    idx = torch.arange(n, device=arc.device)
    follower = order
    leader = order.gather(1, torch.where(idx + 1 < m, idx + 1, 0))
    gap = torch.remainder(arc.gather(1, leader) - arc.gather(1, follower), length_m)
    gap = torch.where(follower == leader, length_m, gap)
    return follower, leader, gap, idx < m


@dataclass(frozen=True)
class PsiTensors:
    """Psi split into named (B,) tensors, plus the scales features are normalised by."""

    v_mean: torch.Tensor
    d_mean: torch.Tensor
    d_min: torch.Tensor
    d_max: torch.Tensor
    v_min: torch.Tensor
    v_max: torch.Tensor
    d_std: torch.Tensor | None = None  # measured spacing std [m] (spacing_dispersion = "measured")

    @classmethod
    def from_array(
        cls,
        psi: np.ndarray | torch.Tensor,
        dtype: torch.dtype = torch.float32,
        d_std: np.ndarray | None = None,
    ) -> PsiTensors:
        p = torch.as_tensor(psi, dtype=dtype)
        return cls(
            *p.unbind(dim=1), d_std=None if d_std is None else torch.as_tensor(d_std, dtype=dtype)
        )

    @classmethod
    def of(cls, snaps: Snapshots, dtype: torch.dtype = torch.float32) -> PsiTensors:
        """Psi of a batch of snapshots, with the dispersion target when they carry one."""
        return cls.from_array(snaps.psi, dtype, snaps.spacing_std_m)

    @cached_property
    def v_range(self) -> torch.Tensor:
        return self.v_max - self.v_min

    @cached_property
    def v_scale(self) -> torch.Tensor:
        return torch.clamp(0.5 * (self.v_max - self.v_min), min=0.1)

    @cached_property
    def static_features(self) -> torch.Tensor:
        """(B, 4) the global features that depend on Psi alone (computed once per batch)."""
        return torch.stack(
            [
                self.d_min / self.d_mean,
                self.d_max / self.d_mean,
                (self.v_max - self.v_min) / self.v_mean,
                (self.v_min + self.v_max - 2 * self.v_mean) / (2 * self.v_scale),
                torch.zeros_like(self.d_mean) if self.d_std is None else self.d_std / self.d_mean,
            ],
            dim=-1,
        )


def scene_gaps(
    arc: torch.Tensor, present: torch.Tensor, length_m: float, anchor: torch.Tensor
) -> tuple[torch.Tensor, ...]:
    """``ring_gaps`` of a scene, plus each gap's start [m] (B, N).

    An empty ring gets one virtual vehicle at ``anchor`` (a random angle) whose gap is the
    whole ring, so the first vehicle of a scene goes anywhere (rotation symmetry).
    """
    n = arc.shape[1]
    virtual = ~present.any(dim=1, keepdim=True) & (torch.arange(n) == 0)
    arc_e = torch.where(virtual, anchor[:, None], arc)
    follower, leader, gap, valid = ring_gaps(arc_e, present | virtual, length_m)
    return follower, leader, gap, valid, arc_e.gather(1, follower)


# Global feature order: remaining, present, d_min, d_max, needed v, mean v, v range, v centre.
_GLOBAL_ORDER = [0, 1, 4, 5, 2, 3, 6, 7, 8]


def features(
    arc: torch.Tensor,
    speed: torch.Tensor,
    present: torch.Tensor,
    remaining: torch.Tensor,
    psi: PsiTensors,
    length_m: float,
    anchor: torch.Tensor,
    geometry: tuple[torch.Tensor, ...] | None = None,
) -> tuple[torch.Tensor, ...]:
    """Per-gap and global features of the current scene (all relative, no labels).

    Returns (gap features (B, N, 7), global features (B, 8), needed speed (B,), geometry);
    ``geometry`` is ``scene_gaps``' result, computed here unless the caller has it.
    """
    n = arc.shape[1]
    m = present.sum(dim=1)
    empty = (m == 0)[:, None]
    if geometry is None:
        geometry = scene_gaps(arc, present, length_m, anchor)
    follower, leader, gap, _, _ = geometry
    vs, vm, dm = psi.v_scale[:, None], psi.v_mean[:, None], psi.d_mean[:, None]
    v_f = torch.where(empty, vm, speed.gather(1, follower))
    v_l = torch.where(empty, vm, speed.gather(1, leader))
    gap_dm = gap / dm
    gap_feat = torch.stack(
        [
            gap_dm,
            (gap - psi.d_min[:, None]) / dm,
            (gap - psi.d_max[:, None]) / dm,
            gap_dm - 1.0 - remaining[:, None] / n,
            (v_f - vm) / vs,
            (v_l - vm) / vs,
            gap / length_m,
        ],
        dim=-1,
    )
    v_sum = (speed * present).sum(dim=1)
    # The mean speed the vehicles still to place need for the fleet to average Psi's mean.
    need_v = (n * psi.v_mean - v_sum) / torch.clamp(remaining, min=1)
    mean_v = torch.where(empty[:, 0], psi.v_mean, v_sum / torch.clamp(m, min=1))
    dynamic = torch.stack(
        [
            remaining / n,
            m / n,
            (need_v - psi.v_mean) / psi.v_scale,
            (mean_v - psi.v_mean) / psi.v_scale,
        ],
        dim=-1,
    )
    glob = torch.cat([dynamic, psi.static_features.to(dynamic.dtype)], dim=-1)[:, _GLOBAL_ORDER]
    return gap_feat, glob, need_v, geometry


class GeneratorNet(nn.Module):
    """Shared MLP scoring every gap: (logit, fraction mean, fraction log-std, speed mean, speed log-std)."""

    def __init__(self, hidden_size: int = 64) -> None:
        super().__init__()
        self.hidden_size = hidden_size
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
    arc: torch.Tensor,
    speed: torch.Tensor,
    present: torch.Tensor,
    remaining: torch.Tensor,
    psi: PsiTensors,
    length_m: float,
    n_samples: int,
    gen: torch.Generator,
    allowed: torch.Tensor | None = None,
    anchor: torch.Tensor | None = None,
    geometry: tuple[torch.Tensor, ...] | None = None,
) -> Proposal:
    """Sample ``n_samples`` candidates for the next hidden vehicle of every scene.

    ``allowed`` (B, N) optionally removes gap choices (in arc order) before sampling.
    ``anchor`` and ``geometry`` (``scene_gaps`` with that anchor) may come from the caller;
    otherwise the anchor is drawn here, first, from ``gen``.
    """
    b = arc.shape[0]
    if anchor is None:
        anchor = torch.rand(b, generator=gen, dtype=arc.dtype) * length_m
    gap_feat, glob, need_v, geometry = features(
        arc, speed, present, remaining, psi, length_m, anchor, geometry
    )
    _, _, gap, valid, start = geometry
    out = net(gap_feat.float(), glob.float())
    if allowed is not None:
        valid = valid & (allowed | ~(allowed & valid).any(dim=1, keepdim=True))
    logits = out[..., 0].masked_fill(~valid, -torch.inf)
    probs = torch.softmax(logits, dim=1)
    choice = torch.multinomial(probs, n_samples, replacement=True, generator=gen)  # (B, S)
    log_p = torch.log_softmax(logits, dim=1)
    pick = out.gather(1, choice[..., None].expand(-1, -1, out.shape[-1])).transpose(0, 1)
    eps = torch.randn(n_samples, b, 2, generator=gen)
    frac = torch.sigmoid(pick[..., 1] + torch.exp(pick[..., 2].clamp(-5, 2)) * eps[..., 0]).clamp(
        1e-3, 1 - 1e-3
    )
    # Speeds live in Psi's [v_min, v_max] by construction (logit-normal on that interval):
    # the paper's loss has no speed-bound term, so an unbounded proposal drifts outside.
    # Centred on the speed the remaining vehicles need for Psi's mean: the MLP adds a residual.
    need = ((need_v - psi.v_min) / psi.v_range.clamp(min=1e-3)).clamp(0.02, 0.98)
    base = torch.logit(need)
    u = torch.sigmoid(base + pick[..., 3] + torch.exp(pick[..., 4].clamp(-6, 1)) * eps[..., 1])
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
    """The paper's L_speed and L_dist terms of completed scenes, (B,) each.

    A (the gaps influenced by generated vehicles) holds every gap whose follower or
    leader was generated. Same definitions as ``macro.spacing_losses`` (numpy). When Psi
    carries the detectors' spacing std ``d_std``, L_var is |std(d_A) - d_std| / d_mean:
    the paper's std(d_A) / d_mean pulls every completion towards equal gaps, which the
    measured spacing distribution contradicts.
    """
    present = torch.ones_like(generated)
    follower, leader, gap, _ = ring_gaps(arc, present, length_m)
    a = (generated.gather(1, follower) | generated.gather(1, leader)).float()
    cnt = a.sum(dim=1).clamp(min=1.0)
    mean = (gap * a).sum(dim=1) / cnt
    dmin, dmax = psi.d_min[:, None], psi.d_max[:, None]
    var = (((gap - mean[:, None]) ** 2) * a).sum(dim=1) / cnt
    has = a.sum(dim=1) > 0
    zero = torch.zeros_like(mean)
    return {
        "L_speed": (speed.mean(dim=1) / psi.v_mean - 1.0) ** 2,
        "L_mean": torch.where(has, (mean / psi.d_mean - 1.0) ** 2, zero),
        "L_min": ((torch.relu(dmin - gap) / dmin) ** 2 * a).sum(dim=1) / cnt,
        "L_max": ((torch.relu(gap - dmax) / dmax) ** 2 * a).sum(dim=1) / cnt,
        # sqrt has an infinite slope at 0: the epsilon keeps equal gaps trainable.
        "L_var": torch.where(
            has, _dispersion(torch.sqrt(var + 1e-8), psi.d_std) / psi.d_mean, zero
        ),
    }


def _dispersion(std: torch.Tensor, target: torch.Tensor | None) -> torch.Tensor:
    if target is None:
        return std
    target = torch.as_tensor(target, dtype=std.dtype)
    return torch.sqrt((std - target) ** 2 + 1e-8)


def total_loss(terms: dict[str, torch.Tensor], lambda_v: float, lambda_d: float) -> torch.Tensor:
    return lambda_v * terms["L_speed"] + lambda_d * (
        terms["L_mean"] + terms["L_min"] + terms["L_max"] + terms["L_var"]
    )


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
    b, n = arc.shape
    log_p = arc.new_zeros(b)
    k = hidden.sum(dim=1)
    for step in range(int(k.max().item()) if b else 0):
        active = k > step
        remaining = (k - step).clamp(min=0)
        prop = propose(net, arc, speed, present, remaining, psi, snaps.length_m, 1, gen)
        slot = _next_hidden_slot(hidden, present)
        onehot = torch.nn.functional.one_hot(slot, n).bool() & active[:, None]
        arc = torch.where(onehot, prop.arc[0][:, None], arc)
        speed = torch.where(onehot, prop.speed[0][:, None], speed)
        present = present | onehot
        log_p = log_p + torch.where(active, prop.log_prob_choice[0], torch.zeros_like(log_p))
    return arc, speed, hidden, log_p


# Inference runs its geometry in float64; this absorbs its rounding, far below the 1e-6 m
# that metrics allow, and is the same for counts and split points so the two agree.
GEOMETRY_TOL_M = 1e-9


def _piece_range(
    x: torch.Tensor, d_min: torch.Tensor, d_max: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fewest and most further vehicles m such that x splits into m + 1 gaps in [d_min, d_max]."""
    lo_m = torch.clamp(torch.ceil((x - GEOMETRY_TOL_M) / d_max) - 1, min=0)
    hi_m = torch.floor((x + GEOMETRY_TOL_M) / d_min) - 1
    return lo_m, hi_m


def _sumset(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """{x + y : x in a, y in b} of count sets held as bool masks over 0..R (truncated at R)."""
    r1 = a.shape[-1]
    # windows[..., x, k] = a[x - (R - k)] (False before 0): pair it with b[R - k].
    windows = torch.nn.functional.pad(a, (r1 - 1, 0)).unfold(-1, r1, 1)
    return (windows & b.flip(-1)[..., None, :]).any(dim=-1)


class SplitTable:
    """What the look-ahead needs that stays the same over the steps of one completion.

    Pairs (c1, c2) count the vehicles still to come behind and ahead of the next one in
    its gap, ordered by c1 + c2 so that the pairs for r vehicles to come are a prefix.
    A split point a1 (distance from the gap's follower) serves (c1, c2) if
    (c1 + 1) d_min <= a1 <= (c1 + 1) d_max and (c2 + 1) d_min <= gap - a1 <= (c2 + 1) d_max.
    """

    def __init__(self, psi: PsiTensors, r_max: int, length_m: float, n: int) -> None:
        c1, c2, self.total, self.counts, self.not_self = _count_pairs(r_max, n, psi.d_min.dtype)
        self.d_min, self.d_max = psi.d_min[:, None], psi.d_max[:, None]
        self.lo1, self.hi1 = (c1 + 1) * self.d_min[..., None], (c1 + 1) * self.d_max[..., None]
        self.lo2, self.hi2 = (c2 + 1) * self.d_max[..., None], (c2 + 1) * self.d_min[..., None]
        ring = torch.full_like(psi.d_min, length_m)
        self.ring_lo, self.ring_hi = _piece_range(ring, psi.d_min, psi.d_max)


@functools.lru_cache(maxsize=64)
def _count_pairs(r_max: int, n: int, dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """(c1, c2, c1 + c2, counts 0..R, not-self mask (N, N, 1)) for ``SplitTable``."""
    pairs = [(c1, t - c1) for t in range(r_max + 1) for c1 in range(t + 1)]
    c1, c2 = torch.tensor(pairs, dtype=dtype).reshape(-1, 2).unbind(dim=1)
    not_self = ~torch.eye(n, dtype=torch.bool)[..., None]
    return c1, c2, (c1 + c2).long(), torch.arange(r_max + 1, dtype=dtype), not_self


@dataclass
class Lookahead:
    """Where the next vehicle may go so that the scene can still be completed within bounds.

    For every current gap j (arc order) and every split of the vehicles still to place
    after this one into c1 behind and c2 ahead of it (the rest going to other gaps), the
    split points a1 (distance from the gap's follower) that leave both new gaps completable
    form the interval [lo, hi]; ``ok`` marks the pairs (c1, c2) the other gaps can match.
    The check is exact: an accepted vehicle never leaves a scene that cannot be finished.
    With none left to place it is the paper's check (both new gaps in [d_min, d_max]).
    """

    lo: torch.Tensor  # (B, N, P) [m]
    hi: torch.Tensor  # (B, N, P) [m]
    ok: torch.Tensor  # (B, N, P)
    empty: torch.Tensor  # (B,) no vehicle yet: the first one goes anywhere
    empty_ok: torch.Tensor  # (B,) ... and then the ring must hold the rest within bounds

    @property
    def allowed(self) -> torch.Tensor:
        """(B, N) gaps with some feasible split point: rejecting the others up front is the
        T_max -> infinity limit of rejection for the discrete part of the proposal."""
        return self.ok.any(dim=2) | self.empty[:, None]

    def accepts(self, choice: torch.Tensor, a1: torch.Tensor) -> torch.Tensor:
        """(S, B) whether candidates (gap ``choice``, split point ``a1``) pass the check."""
        idx = choice.T[..., None].expand(-1, -1, self.lo.shape[-1])  # (B, S, P)
        lo, hi, ok = self.lo.gather(1, idx), self.hi.gather(1, idx), self.ok.gather(1, idx)
        a = a1.T[..., None]
        inside = (ok & (a >= lo - GEOMETRY_TOL_M) & (a <= hi + GEOMETRY_TOL_M)).any(dim=-1).T
        return inside | (self.empty & self.empty_ok)

    def project(self, choice: torch.Tensor, a1: torch.Tensor) -> torch.Tensor:
        """(B,) the feasible split point of gap ``choice`` nearest to ``a1`` (a1 if none)."""
        idx = choice[:, None, None].expand(-1, 1, self.lo.shape[-1])
        lo, hi, ok = (t.gather(1, idx)[:, 0] for t in (self.lo, self.hi, self.ok))
        near = torch.minimum(torch.maximum(a1[:, None], lo), hi)
        dist = torch.where(ok, (near - a1[:, None]).abs(), torch.inf)
        best = near.gather(1, dist.argmin(dim=1, keepdim=True))[:, 0]
        return torch.where(ok.any(dim=1) & ~self.empty, best, a1)


def lookahead(
    table: SplitTable,
    geometry: tuple[torch.Tensor, ...],
    present: torch.Tensor,
    generated: torch.Tensor,
    rem_after: torch.Tensor,
) -> Lookahead:
    """The exact feasibility check for placing one more vehicle, ``rem_after`` still to come.

    ``geometry`` is ``scene_gaps`` of the scene. A touched gap (a generated vehicle at
    either end) must end as gaps in [d_min, d_max], so it takes c in [lo, hi] further
    vehicles; an untouched gap (two observed vehicles) may stay as it is or take c >= 1 if
    its pieces then fit. The counts the other gaps can absorb together are a sum of these
    sets (a small dynamic programme over 0..R).
    """
    follower, leader, gap, valid, _ = geometry
    b, n = gap.shape
    r_max = int(rem_after.max()) if b else 0
    counts = table.counts[: r_max + 1]
    n_pairs = (r_max + 1) * (r_max + 2) // 2
    lo_c, hi_c = _piece_range(gap, table.d_min, table.d_max)
    fits = (counts >= lo_c[..., None]) & (counts <= hi_c[..., None])
    touched = valid & (generated.gather(1, follower) | generated.gather(1, leader))
    zero = counts == 0
    sets = torch.where(touched[..., None], fits, (fits & valid[..., None]) | zero)
    # rest[:, j]: the counts all gaps but j can absorb together.
    if r_max == 0:  # none to come: every other gap must be able to stay as it is
        lacks = (~sets[..., 0]).long()
        rest = (lacks.sum(dim=1, keepdim=True) == lacks)[..., None]
    else:
        rest = zero.expand(b, n, r_max + 1)
        for i in range(int(valid.sum(dim=1).max()) if b else 0):
            rest = _sumset(rest, torch.where(table.not_self[i], sets[:, i : i + 1], zero))
    need = rem_after[:, None] - table.total[:n_pairs]  # (B, P): what the other gaps absorb
    ok = (need >= 0)[:, None, :] & rest.gather(
        2, need.clamp(min=0)[:, None, :].expand(b, n, n_pairs)
    )
    g = gap[..., None]
    lo = torch.maximum(table.lo1[..., :n_pairs], g - table.lo2[..., :n_pairs])
    hi = torch.minimum(table.hi1[..., :n_pairs], g - table.hi2[..., :n_pairs])
    ok = ok & valid[..., None] & (lo <= hi + 2 * GEOMETRY_TOL_M)
    empty_ok = (table.ring_lo <= rem_after) & (rem_after <= table.ring_hi)
    return Lookahead(lo, hi, ok, ~present.any(dim=1), empty_ok)


@dataclass
class Completion:
    arc_m: np.ndarray
    speed_mps: np.ndarray
    projected: np.ndarray  # (B,) number of hidden vehicles that needed projection
    wall_s: float


@torch.inference_mode()
def complete(net: GeneratorNet, snaps: Snapshots, t_max: int, seed: int) -> Completion:
    """Algorithm 3, batched: rejection sampling against Psi's bounds, projection as fallback."""
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(int(seed))
    hidden = torch.as_tensor(snaps.hidden)
    present = ~hidden
    # Geometry in float64 (the network still sees float32 features): accepted gaps are
    # then within Psi's bounds to rounding, not to float32's ~1e-4 m on a ring.
    arc = torch.as_tensor(snaps.arc_m, dtype=torch.float64).masked_fill(hidden, 0.0)
    speed = torch.as_tensor(snaps.speed_mps, dtype=torch.float64).masked_fill(hidden, 0.0)
    psi = PsiTensors.of(snaps, dtype=torch.float64)
    length = snaps.length_m
    b, n = arc.shape
    k = hidden.sum(dim=1)
    k_max = int(k.max()) if b else 0
    table = SplitTable(psi, max(k_max - 1, 0), length, n)
    projected = torch.zeros(b, dtype=torch.long)
    rank = hidden.cumsum(dim=1).masked_fill(~hidden, 0)  # hidden slots fill in slot order
    for step in range(k_max):
        active = k > step
        rem_after = (k - step - 1).clamp(min=0)
        anchor = torch.rand(b, generator=gen, dtype=torch.float64) * length
        geometry = scene_gaps(arc, present, length, anchor)
        look = lookahead(table, geometry, present, hidden & present, rem_after)
        prop = propose(
            net,
            arc,
            speed,
            present,
            k - step,
            psi,
            length,
            t_max,
            gen,
            look.allowed,
            anchor,
            geometry,
        )
        a1 = prop.frac * prop.gap
        ok = look.accepts(prop.gap_pos, a1) & (prop.speed >= psi.v_min) & (prop.speed <= psi.v_max)
        any_ok = ok.any(dim=0)
        # The first accepted candidate, else the last one, projected: the nearest split
        # point of its gap that passes, its speed clipped to the bounds.
        pick = torch.where(any_ok, ok.byte().argmax(dim=0), t_max - 1)[None]
        new_arc, new_v = prop.arc.gather(0, pick)[0], prop.speed.gather(0, pick)[0]
        if not bool(any_ok.all()):
            a = a1.gather(0, pick)[0]
            a_proj = look.project(prop.gap_pos.gather(0, pick)[0], a)
            new_arc = torch.where(any_ok, new_arc, torch.remainder(new_arc - a + a_proj, length))
            new_v = torch.where(
                any_ok, new_v, torch.minimum(torch.maximum(new_v, psi.v_min), psi.v_max)
            )
            projected += active & ~any_ok
        onehot = rank == step + 1
        arc = torch.where(onehot, new_arc[:, None], arc)
        speed = torch.where(onehot, new_v[:, None], speed)
        present = present | onehot
    # Observed vehicles never move: the input values, bit for bit.
    arc_out = np.where(snaps.hidden, arc.numpy() % length, snaps.arc_m)
    speed_out = np.where(snaps.hidden, speed.numpy(), snaps.speed_mps)
    return Completion(arc_out, speed_out, projected.numpy(), time.perf_counter() - t0)


# --------------------------------------------------------------------------- baselines


def complete_uniform(snaps: Snapshots, seed: int) -> Completion:
    """Baseline: hidden vehicles at uniform random positions and speeds within Psi's bounds."""
    t0 = time.perf_counter()
    rng = np.random.default_rng([seed, 101])
    b, n = snaps.arc_m.shape
    arc = np.where(snaps.hidden, rng.uniform(0, snaps.length_m, (b, n)), snaps.arc_m)
    v = rng.uniform(snaps.psi[:, 4:5], snaps.psi[:, 5:6], (b, n))
    speed = np.where(snaps.hidden, v, snaps.speed_mps)
    return Completion(arc, speed, np.zeros(b, dtype=int), time.perf_counter() - t0)


def complete_equal_gap(snaps: Snapshots, seed: int) -> Completion:
    """Baseline: water-fill the observed gaps with evenly spaced vehicles at the speed
    that makes the fleet mean equal Psi's mean speed (clipped to the bounds)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng([seed, 202])
    b, n = snaps.arc_m.shape
    arc = snaps.arc_m.copy()
    speed = snaps.speed_mps.copy()
    length = snaps.length_m
    for i in range(b):
        hid = np.flatnonzero(snaps.hidden[i])
        k = len(hid)
        if k == 0:
            continue
        obs = np.sort(snaps.arc_m[i, ~snaps.hidden[i]])
        if len(obs) == 0:
            starts, arcs = np.array([rng.uniform(0, length)]), np.array([length])
            counts = np.array([k - 1])
        else:
            starts = obs
            arcs = np.mod(np.roll(obs, -1) - obs, length)
            arcs[arcs == 0] = length if len(obs) == 1 else 0.0
            counts = np.zeros(len(obs), dtype=int)
            for _ in range(k):
                counts[np.argmax(arcs / (counts + 1))] += 1
        pos = []
        for s0, ln, c in zip(starts, arcs, counts, strict=True):
            if len(obs) == 0:
                pos += [s0 + ln * j / k for j in range(k)]
            else:
                pos += [s0 + ln * j / (c + 1) for j in range(1, c + 1)]
        arc[i, hid] = np.mod(pos, length)
        v_obs = snaps.speed_mps[i, ~snaps.hidden[i]].sum()
        speed[i, hid] = np.clip((n * snaps.psi[i, 0] - v_obs) / k, snaps.psi[i, 4], snaps.psi[i, 5])
    return Completion(arc, speed, np.zeros(b, dtype=int), time.perf_counter() - t0)


# --------------------------------------------------------------------------- metrics


def feasible_exists(snaps: Snapshots) -> np.ndarray:
    """(B,) whether any completion puts every touched gap and speed within Psi's bounds."""
    out = np.zeros(len(snaps), dtype=bool)
    for i in range(len(snaps)):
        d_min, d_max, v_min, v_max = snaps.psi[i, 2:6]
        k = int(snaps.hidden[i].sum())
        if v_min > v_max or d_min > d_max:
            continue
        obs = np.sort(snaps.arc_m[i, ~snaps.hidden[i]])
        if k == 0:
            out[i] = True
            continue
        if len(obs) == 0:
            out[i] = k * d_min <= snaps.length_m <= k * d_max
            continue
        arcs = np.mod(np.roll(obs, -1) - obs, snaps.length_m)
        if len(obs) == 1:
            arcs = np.array([snaps.length_m])
        reachable = {0}
        for ln in arcs:
            options = [0] + [c for c in range(1, k + 1) if (c + 1) * d_min <= ln <= (c + 1) * d_max]
            reachable = {r + c for r in reachable for c in options if r + c <= k}
        out[i] = k in reachable
    return out


def _ring_spacing_std(arc_m: np.ndarray, length_m: float) -> np.ndarray:
    """Std of all spacings of each completed ring, (B,)."""
    s = np.sort(np.mod(arc_m, length_m), axis=1)
    gaps = np.diff(np.concatenate([s, s[:, :1] + length_m], axis=1), axis=1)
    return gaps.std(axis=1)


def completion_metrics(snaps: Snapshots, comp: Completion) -> pd.DataFrame:
    """Per snapshot: feasibility, macro errors, each L term, matched hidden-state errors."""
    terms = macro_losses(
        torch.as_tensor(comp.arc_m, dtype=torch.float64),
        torch.as_tensor(comp.speed_mps, dtype=torch.float64),
        torch.as_tensor(snaps.hidden),
        PsiTensors.of(snaps, dtype=torch.float64),
        snaps.length_m,
    )
    length = snaps.length_m
    b = len(snaps)
    in_bounds = np.zeros(b, dtype=bool)
    pos_err = np.full(b, np.nan)
    spd_err = np.full(b, np.nan)
    mean_spacing = np.full(b, length / snaps.arc_m.shape[1])
    for i in range(b):
        hid = snaps.hidden[i]
        s = np.mod(comp.arc_m[i], length)
        order = np.argsort(s)
        gaps = np.mod(np.roll(s[order], -1) - s[order], length)
        gaps[gaps == 0] = length if len(s) == 1 else 0.0
        touched = hid[order] | np.roll(hid[order], -1)
        d_min, d_max, v_min, v_max = snaps.psi[i, 2:6]
        g_ok = np.all((gaps[touched] >= d_min - 1e-6) & (gaps[touched] <= d_max + 1e-6))
        v = comp.speed_mps[i, hid]
        in_bounds[i] = g_ok and np.all((v >= v_min - 1e-6) & (v <= v_max + 1e-6))
        idx = np.flatnonzero(hid)
        if len(idx):
            da = np.abs(
                np.mod(
                    comp.arc_m[i, idx][:, None] - snaps.arc_m[i, idx][None, :] + length / 2, length
                )
                - length / 2
            )
            dv = np.abs(comp.speed_mps[i, idx][:, None] - snaps.speed_mps[i, idx][None, :])
            r, c = linear_sum_assignment(
                da / snaps.psi[i, 1] + dv / max(snaps.psi[i, 5] - snaps.psi[i, 4], 0.1)
            )
            pos_err[i], spd_err[i] = da[r, c].mean(), dv[r, c].mean()
    return pd.DataFrame(
        {
            "run": snaps.run,
            "time_s": snaps.time_s,
            "K": snaps.k,
            "feasible_exists": feasible_exists(snaps),
            "projected": comp.projected,
            # Algorithm 3 without projection met the bounds (the strict measure) ...
            "feasible": in_bounds & (comp.projected == 0),
            # ... and the completion meets them, projected vehicles included.
            "in_bounds": in_bounds,
            "speed_rel_err": np.abs(comp.speed_mps.mean(axis=1) - snaps.psi[:, 0])
            / snaps.psi[:, 0],
            "spacing_rel_err": np.abs(mean_spacing - snaps.psi[:, 1]) / snaps.psi[:, 1],
            "spacing_std_m": _ring_spacing_std(comp.arc_m, snaps.length_m),
            "true_spacing_std_m": _ring_spacing_std(snaps.arc_m, snaps.length_m),
            **{k: v.numpy() for k, v in terms.items()},
            "pos_err_m": pos_err,
            "speed_err_mps": spd_err,
        }
    )


def summarise_metrics(per_snapshot: pd.DataFrame) -> pd.DataFrame:
    """generator_metrics.csv: one row per method and K."""
    rows = []
    for (method, k), g in per_snapshot.groupby(["method", "K"], sort=True):
        fe = g["feasible_exists"]
        rows.append(
            {
                "method": method,
                "K": k,
                "n_snapshots": len(g),
                "n_feasible_exists": int(fe.sum()),
                "n_no_feasible": int((~fe).sum()),
                "feasibility_rate": float(g.loc[fe, "feasible"].mean()) if fe.any() else np.nan,
                "in_bounds_rate": float(g.loc[fe, "in_bounds"].mean()) if fe.any() else np.nan,
                "projected_vehicles": int(g["projected"].sum()),
                "speed_rel_err": g["speed_rel_err"].mean(),
                "spacing_rel_err": g["spacing_rel_err"].mean(),
                "spacing_std_m": np.sqrt((g["spacing_std_m"] ** 2).mean()),
                "true_spacing_std_m": np.sqrt((g["true_spacing_std_m"] ** 2).mean()),
                **{t: g[t].mean() for t in LOSS_TERMS},
                "pos_err_m": g["pos_err_m"].mean(),
                "speed_err_mps": g["speed_err_mps"].mean(),
            }
        )
    return pd.DataFrame(rows)

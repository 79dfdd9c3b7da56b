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

A gap's features include what the exact look-ahead (below) knows about it: whether it
is touched (a generated vehicle at either end), how many vehicles it must and can still
take within [d_min, d_max] relative to the vehicles still to place, whether the next
vehicle may go into it at all, and the range of its feasible split points (in the
position head's logit units). Without them the network scores gaps blind to how many
vehicles each can or must still take (FEATURE_VERSION 3).

Training minimises L_gen = lambda_v L_speed + lambda_d (L_mean + L_min + L_max + L_var)
(+ lambda_rec L_rec as a switch). Gradients reach the positions and speeds through the
reparameterised samples; the discrete gap choice gets the score-function (REINFORCE)
gradient of the same loss with a batch-mean baseline, which is the unbiased estimator
for a discrete choice inside a stochastic computation graph. The look-ahead features are
detached (counts are integers; the split range is a geometric input).

Inference is Algorithm 3, batched over snapshots: every step proposes T_max candidates at
once (the proposal distribution does not change between trials, so this equals
resampling one at a time) and keeps the first whose touched gaps and speed are within
bounds; if none is, the last candidate is projected onto the nearest feasible point and
counted. A touched gap that will still receive vehicles is judged by what it can hold:
it must split into m + 1 gaps in [d_min, d_max] for some m <= vehicles still to place
(the paper's check when none remain; without it a whole scene, K = N, could never start).

Extension (``complete(..., truncate=True)``, the default): each trial is drawn from the
proposal restricted to the split points that pass the check, the T_max -> infinity limit
of rejection. Gap j is chosen with probability proportional to p_j m_j (p_j the network's
choice probability, m_j the mass its position distribution puts on gap j's feasible split
points) and the split point from the logit-normal truncated to them (inverse CDF, in log
space so that any tail is exact). The check still judges every candidate and projection
stays the counted fallback (a scene whose proposal has no feasible mass at all).
``truncate=False`` is the plain Algorithm 3. ``Completion.accept_prob`` keeps, per step,
the probability that one plain trial would have passed (sum_j p_j m_j), so how much the
truncation does is on record (``rejection_success``).

Inference runs in numpy (float64 geometry, the MLP in float32 with the trained weights):
a K = 4 completion of one snapshot is some 200 tiny array operations, and numpy's
per-operation overhead is a third of torch's. Geometry and features are one definition
for both backends (``_xp``); training runs them in torch, with gradients.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import pandas as pd
import torch
from scipy.optimize import linear_sum_assignment
from scipy.special import log_ndtr, ndtri_exp
from torch import nn

from macromicro_sumo.dataset import Snapshots

FEATURE_VERSION = 3
N_GAP_FEATURES = 13
N_GLOBAL_FEATURES = 9
LOSS_TERMS = ("L_speed", "L_mean", "L_min", "L_max", "L_var")
# Limits of the position head's log-std and of the split-range features (logit units).
FRAC_LOG_STD = (-5.0, 2.0)
SPEED_LOG_STD = (-6.0, 1.0)
LOGIT_CLIP = 5.0


def _xp(x: Any) -> Any:
    """The array module of ``x``: geometry and features run on torch (training, with
    gradients) and numpy (inference) from one definition."""
    return torch if isinstance(x, torch.Tensor) else np


def _take(x: Any, idx: Any) -> Any:
    """x[b, idx[b, i]] along axis 1."""
    if isinstance(x, torch.Tensor):
        return x.gather(1, idx)
    return np.take_along_axis(x, idx, axis=1)


# --------------------------------------------------------------------------- scene geometry


def ring_gaps(arc: Any, present: Any, length_m: float) -> tuple[Any, ...]:
    """Gaps of the present vehicles in arc order, batched over rows (torch or numpy).

    Returns (follower slot, leader slot, gap [m], valid) each (B, N): position i holds
    the i-th gap in arc order; positions >= the number of present vehicles are invalid.
    A lone vehicle's gap is the whole ring.
    """
    xp = _xp(arc)
    n = arc.shape[1]
    order = xp.argsort(xp.where(present, arc, arc + 4 * length_m), 1)
    m = present.sum(1)[:, None]
    idx = xp.arange(n)
    follower = order
    leader = _take(order, xp.where(idx + 1 < m, idx + 1, 0))
    gap = (_take(arc, leader) - _take(arc, follower)) % length_m
    gap = xp.where(follower == leader, length_m, gap)
    return follower, leader, gap, idx < m


@dataclass(frozen=True)
class PsiTensors:
    """Psi split into named (B,) arrays (torch or numpy), plus the scales features use."""

    v_mean: Any
    d_mean: Any
    d_min: Any
    d_max: Any
    v_min: Any
    v_max: Any
    d_std: Any = None  # measured spacing std [m] (spacing_dispersion = "measured")

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

    @classmethod
    def arrays(cls, snaps: Snapshots) -> PsiTensors:
        """The same as float64 numpy arrays (inference)."""
        d_std = snaps.spacing_std_m
        return cls(
            *np.asarray(snaps.psi, dtype=np.float64).T,
            d_std=None if d_std is None else np.asarray(d_std, dtype=np.float64),
        )

    @cached_property
    def v_range(self) -> Any:
        return self.v_max - self.v_min

    @cached_property
    def v_scale(self) -> Any:
        return _xp(self.v_max).clip(0.5 * (self.v_max - self.v_min), 0.1, None)

    @cached_property
    def static_features(self) -> Any:
        """(B, 5) the global features that depend on Psi alone (computed once per batch)."""
        xp = _xp(self.d_mean)
        d_std = xp.zeros_like(self.d_mean) if self.d_std is None else self.d_std
        return xp.stack(
            [
                self.d_min / self.d_mean,
                self.d_max / self.d_mean,
                (self.v_max - self.v_min) / self.v_mean,
                (self.v_min + self.v_max - 2 * self.v_mean) / (2 * self.v_scale),
                d_std / self.d_mean,
            ],
            -1,
        )


def scene_gaps(arc: Any, present: Any, length_m: float, anchor: Any) -> tuple[Any, ...]:
    """``ring_gaps`` of a scene, plus each gap's start [m] (B, N).

    An empty ring gets one virtual vehicle at ``anchor`` (a random angle) whose gap is the
    whole ring, so the first vehicle of a scene goes anywhere (rotation symmetry).
    """
    xp = _xp(arc)
    n = arc.shape[1]
    virtual = ~present.any(1)[:, None] & (xp.arange(n) == 0)
    arc_e = xp.where(virtual, anchor[:, None], arc)
    follower, leader, gap, valid = ring_gaps(arc_e, present | virtual, length_m)
    return follower, leader, gap, valid, _take(arc_e, follower)


# --------------------------------------------------------------------------- look-ahead

# Inference runs its geometry in float64; this absorbs its rounding, far below the 1e-6 m
# that metrics allow, and is the same for counts and split points so the two agree.
GEOMETRY_TOL_M = 1e-9


def _piece_range(x: np.ndarray, d_min: np.ndarray, d_max: np.ndarray) -> tuple[np.ndarray, ...]:
    """Fewest and most further vehicles m such that x splits into m + 1 gaps in [d_min, d_max]."""
    lo_m = np.maximum(np.ceil((x - GEOMETRY_TOL_M) / d_max) - 1, 0)
    hi_m = np.floor((x + GEOMETRY_TOL_M) / d_min) - 1
    return lo_m, hi_m


@functools.lru_cache(maxsize=16)
def _sum_matrix(r1: int) -> np.ndarray:
    """(r1 * r1, r1) bool: pair (x, y) -> count x + y (dropped beyond r1 - 1)."""
    x, y = np.divmod(np.arange(r1 * r1), r1)
    return (x + y)[:, None] == np.arange(r1)


def _sumset(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """{x + y : x in a, y in b} of count sets held as bool masks over 0..R (truncated at R)."""
    r1 = a.shape[-1]
    outer = a[..., :, None] & b[..., None, :]
    return outer.reshape(*outer.shape[:-2], r1 * r1) @ _sum_matrix(r1)


@functools.lru_cache(maxsize=64)
def _count_pairs(r_max: int, n: int) -> tuple[np.ndarray, ...]:
    """(c1, c2, c1 + c2, counts 0..R, not-self mask (N, N, 1)) for ``SplitTable``."""
    pairs = np.array([(c1, t - c1) for t in range(r_max + 1) for c1 in range(t + 1)], float)
    c1, c2 = pairs.reshape(-1, 2).T
    not_self = ~np.eye(n, dtype=bool)[..., None]
    return c1, c2, (c1 + c2).astype(int), np.arange(r_max + 1), not_self


class SplitTable:
    """What the look-ahead needs that stays the same over the steps of one completion.

    Pairs (c1, c2) count the vehicles still to come behind and ahead of the next one in
    its gap, ordered by c1 + c2 so that the pairs for r vehicles to come are a prefix.
    A split point a1 (distance from the gap's follower) serves (c1, c2) if
    (c1 + 1) d_min <= a1 <= (c1 + 1) d_max and (c2 + 1) d_min <= gap - a1 <= (c2 + 1) d_max.
    """

    def __init__(
        self, d_min: np.ndarray, d_max: np.ndarray, r_max: int, length_m: float, n: int
    ) -> None:
        d_min = np.asarray(d_min, dtype=np.float64)
        d_max = np.asarray(d_max, dtype=np.float64)
        c1, c2, self.total, self.counts, self.not_self = _count_pairs(r_max, n)
        self.d_min, self.d_max = d_min[:, None], d_max[:, None]
        self.lo1, self.hi1 = (c1 + 1) * d_min[:, None, None], (c1 + 1) * d_max[:, None, None]
        self.lo2, self.hi2 = (c2 + 1) * d_max[:, None, None], (c2 + 1) * d_min[:, None, None]
        self.ring_lo, self.ring_hi = _piece_range(np.full_like(d_min, length_m), d_min, d_max)


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

    lo: np.ndarray  # (B, N, P) [m]
    hi: np.ndarray  # (B, N, P) [m]
    ok: np.ndarray  # (B, N, P)
    empty: np.ndarray  # (B,) no vehicle yet: the first one goes anywhere
    empty_ok: np.ndarray  # (B,) ... and then the ring must hold the rest within bounds
    gap: np.ndarray  # (B, N) [m]
    touched: np.ndarray  # (B, N) a generated vehicle at either end
    lo_c: np.ndarray  # (B, N) fewest further vehicles for pieces <= d_max
    hi_c: np.ndarray  # (B, N) most further vehicles for pieces >= d_min

    @cached_property
    def allowed(self) -> np.ndarray:
        """(B, N) gaps with some feasible split point: rejecting the others up front is the
        T_max -> infinity limit of rejection for the discrete part of the proposal."""
        return self.ok.any(axis=2) | self.empty[:, None]

    def gap_features(self, remaining: np.ndarray, n: int) -> np.ndarray:
        """(B, N, 6) per-gap features: touched; fewest and most vehicles the gap can take,
        less the vehicles still to place (this one included), / N; whether the next vehicle
        may go into it; its feasible split range as logits of the gap fraction / LOGIT_CLIP."""
        rem = np.asarray(remaining, dtype=np.float64)[:, None]
        any_ok = self.ok.any(axis=2)
        with np.errstate(divide="ignore", invalid="ignore"):
            lo = np.where(self.ok, self.lo, np.inf).min(axis=2) / self.gap
            hi = np.where(self.ok, self.hi, -np.inf).max(axis=2) / self.gap
            rng = np.log(np.stack([lo, hi], -1)) - np.log1p(-np.stack([lo, hi], -1))
        rng = np.where(any_ok[..., None], np.clip(rng, -LOGIT_CLIP, LOGIT_CLIP), 0.0)
        allowed = np.where(self.empty[:, None], self.empty_ok[:, None], any_ok)
        return np.concatenate(
            [
                np.stack(
                    [
                        self.touched,
                        (np.clip(self.lo_c, 0, n) - rem) / n,
                        (np.clip(self.hi_c, -1, n) - rem) / n,
                        allowed,
                    ],
                    -1,
                ),
                rng / LOGIT_CLIP,
            ],
            -1,
        )

    def accepts(self, choice: np.ndarray, a1: np.ndarray) -> np.ndarray:
        """(B, S) whether candidates (gap ``choice``, split point ``a1``) pass the check."""
        rows = np.arange(len(choice))[:, None]
        lo, hi, ok = self.lo[rows, choice], self.hi[rows, choice], self.ok[rows, choice]
        a = a1[..., None]
        inside = (ok & (a >= lo - GEOMETRY_TOL_M) & (a <= hi + GEOMETRY_TOL_M)).any(axis=-1)
        return inside | (self.empty & self.empty_ok)[:, None]

    def project(self, choice: np.ndarray, a1: np.ndarray) -> np.ndarray:
        """(B,) the feasible split point of gap ``choice`` nearest to ``a1`` (a1 if none)."""
        rows = np.arange(len(choice))
        lo, hi, ok = self.lo[rows, choice], self.hi[rows, choice], self.ok[rows, choice]
        near = np.minimum(np.maximum(a1[:, None], lo), hi)
        dist = np.where(ok, np.abs(near - a1[:, None]), np.inf)
        best = np.take_along_axis(near, dist.argmin(axis=1)[:, None], axis=1)[:, 0]
        return np.where(ok.any(axis=1) & ~self.empty, best, a1)


def lookahead(
    table: SplitTable,
    geometry: tuple[np.ndarray, ...],
    present: np.ndarray,
    generated: np.ndarray,
    rem_after: np.ndarray,
) -> Lookahead:
    """The exact feasibility check for placing one more vehicle, ``rem_after`` still to come.

    ``geometry`` is ``scene_gaps`` of the scene (numpy). A touched gap (a generated vehicle
    at either end) must end as gaps in [d_min, d_max], so it takes c in [lo, hi] further
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
    touched = valid & (_take(generated, follower) | _take(generated, leader))
    zero = counts == 0
    sets = np.where(touched[..., None], fits, (fits & valid[..., None]) | zero)
    # rest[:, j]: the counts all gaps but j can absorb together.
    if r_max == 0:  # none to come: every other gap must be able to stay as it is
        lacks = (~sets[..., 0]).astype(int)
        rest = (lacks.sum(axis=1, keepdims=True) == lacks)[..., None]
    else:
        rest = np.broadcast_to(zero, (b, n, r_max + 1))
        for i in range(int(valid.sum(axis=1).max()) if b else 0):
            rest = _sumset(rest, np.where(table.not_self[i], sets[:, i : i + 1], zero))
    need = rem_after[:, None] - table.total[:n_pairs]  # (B, P): what the other gaps absorb
    ok = (need >= 0)[:, None, :] & np.take_along_axis(
        rest, np.broadcast_to(np.maximum(need, 0)[:, None, :], (b, n, n_pairs)), axis=2
    )
    g = gap[..., None]
    lo = np.maximum(table.lo1[..., :n_pairs], g - table.lo2[..., :n_pairs])
    hi = np.minimum(table.hi1[..., :n_pairs], g - table.hi2[..., :n_pairs])
    ok = ok & valid[..., None] & (lo <= hi + 2 * GEOMETRY_TOL_M)
    empty_ok = (table.ring_lo <= rem_after) & (rem_after <= table.ring_hi)
    return Lookahead(lo, hi, ok, ~present.any(axis=1), empty_ok, gap, touched, lo_c, hi_c)


# --------------------------------------------------------------------------- features


# Global feature order: remaining, present, d_min, d_max, needed v, mean v, v range, v centre.
_GLOBAL_ORDER = [0, 1, 4, 5, 2, 3, 6, 7, 8]


def features(
    arc: Any,
    speed: Any,
    present: Any,
    remaining: Any,
    psi: PsiTensors,
    length_m: float,
    geometry: tuple[Any, ...],
    look_feat: Any,
) -> tuple[Any, ...]:
    """Per-gap and global features of the current scene (all relative, no labels).

    ``geometry`` is ``scene_gaps``' result and ``look_feat`` ``Lookahead.gap_features``,
    both of the same backend as ``arc``. Returns (gap features (B, N, 13), global features
    (B, 9), the mean speed the vehicles still to place need (B,)).
    """
    xp = _xp(arc)
    n = arc.shape[1]
    m = present.sum(1)
    empty = (m == 0)[:, None]
    follower, leader, gap, _, _ = geometry
    vs, vm, dm = psi.v_scale[:, None], psi.v_mean[:, None], psi.d_mean[:, None]
    v_f = xp.where(empty, vm, _take(speed, follower))
    v_l = xp.where(empty, vm, _take(speed, leader))
    gap_dm = gap / dm
    base = xp.stack(
        [
            gap_dm,
            (gap - psi.d_min[:, None]) / dm,
            (gap - psi.d_max[:, None]) / dm,
            gap_dm - 1.0 - remaining[:, None] / n,
            (v_f - vm) / vs,
            (v_l - vm) / vs,
            gap / length_m,
        ],
        -1,
    )
    v_sum = (speed * present).sum(1)
    # The mean speed the vehicles still to place need for the fleet to average Psi's mean.
    need_v = (n * psi.v_mean - v_sum) / xp.clip(remaining, 1, None)
    mean_v = xp.where(empty[:, 0], psi.v_mean, v_sum / xp.clip(m, 1, None))
    dynamic = xp.stack(
        [
            remaining / n,
            m / n,
            (need_v - psi.v_mean) / psi.v_scale,
            (mean_v - psi.v_mean) / psi.v_scale,
        ],
        -1,
    )
    glob = xp.concatenate([dynamic, psi.static_features], -1)[:, _GLOBAL_ORDER]
    return xp.concatenate([base, look_feat], -1), glob, need_v


@dataclass
class Observation:
    """What one autoregressive step sees."""

    geometry: tuple[Any, ...]
    look: Lookahead
    gap_feat: Any
    glob: Any
    need_v: Any


def observe(
    arc: Any,
    speed: Any,
    present: Any,
    generated: Any,
    remaining: Any,
    psi: PsiTensors,
    length_m: float,
    anchor: Any,
    table: SplitTable | None = None,
) -> Observation:
    """Geometry, exact look-ahead and features of a scene (torch or numpy inputs).

    ``remaining`` counts the vehicles still to place, the next one included. ``table``
    may come from the caller (it only depends on Psi and the largest K).
    """
    geometry = scene_gaps(arc, present, length_m, anchor)
    if isinstance(arc, torch.Tensor):
        geo_np = tuple(t.detach().numpy() for t in geometry)
        present_np, generated_np = present.numpy(), generated.numpy()
        rem_np = remaining.numpy()
    else:
        geo_np, present_np, generated_np, rem_np = geometry, present, generated, remaining
    rem_after = np.maximum(rem_np - 1, 0)
    if table is None:
        d_min, d_max = (np.asarray(_numpy(x), dtype=np.float64) for x in (psi.d_min, psi.d_max))
        table = SplitTable(
            d_min, d_max, int(rem_after.max()) if len(rem_after) else 0, length_m, arc.shape[1]
        )
    look = lookahead(table, geo_np, present_np, generated_np, rem_after)
    look_feat = look.gap_features(rem_np, arc.shape[1])
    import os  # TEMP experiment
    if os.environ.get("NOLOOKFEAT"):
        look_feat = look_feat * 0.0
    if isinstance(arc, torch.Tensor):
        look_feat = torch.from_numpy(look_feat).to(arc.dtype)
    gap_feat, glob, need_v = features(
        arc, speed, present, remaining, psi, length_m, geometry, look_feat
    )
    return Observation(geometry, look, gap_feat, glob, need_v)


def _numpy(x: Any) -> np.ndarray:
    return x.detach().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


# --------------------------------------------------------------------------- model


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

    def forward_numpy(self, gap_feat: np.ndarray, glob: np.ndarray) -> np.ndarray:
        """``forward`` in float32 numpy (inference): the global features enter the first
        layer once per scene instead of once per gap."""
        w1, b1, w2, b2, w3, b3 = (p.detach().numpy() for p in self.body.parameters())
        f = gap_feat.shape[-1]
        x, g = gap_feat.astype(np.float32), glob.astype(np.float32)
        h = np.tanh(x @ w1[:, :f].T + (g @ w1[:, f:].T + b1)[:, None, :])
        h = np.tanh(h @ w2.T + b2)
        return h @ w3.T + b3


def _speed_base(need_v: Any, psi: PsiTensors) -> Any:
    """Logit of the speed the remaining vehicles need, on Psi's [v_min, v_max].

    Speeds live in Psi's [v_min, v_max] by construction (logit-normal on that interval):
    the paper's loss has no speed-bound term, so an unbounded proposal drifts outside.
    Centred on the speed the remaining vehicles need for Psi's mean: the MLP adds a residual.
    """
    xp = _xp(need_v)
    need = xp.clip((need_v - psi.v_min) / xp.clip(psi.v_range, 1e-3, None), 0.02, 0.98)
    return xp.log(need) - xp.log1p(-need)


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
) -> Proposal:
    """Sample ``n_samples`` candidates for the next hidden vehicle of every scene (torch,
    reparameterised: the training rollout). ``allowed`` (B, N) optionally removes gap
    choices (in arc order) before sampling."""
    _, _, gap, valid, start = obs.geometry
    b = gap.shape[0]
    out = net(obs.gap_feat.float(), obs.glob.float())
    if allowed is not None:
        valid = valid & (allowed | ~(allowed & valid).any(dim=1, keepdim=True))
    logits = out[..., 0].masked_fill(~valid, -torch.inf)
    probs = torch.softmax(logits, dim=1)
    choice = torch.multinomial(probs, n_samples, replacement=True, generator=gen)  # (B, S)
    log_p = torch.log_softmax(logits, dim=1)
    pick = out.gather(1, choice[..., None].expand(-1, -1, out.shape[-1])).transpose(0, 1)
    eps = torch.randn(n_samples, b, 2, generator=gen)
    frac = torch.sigmoid(pick[..., 1] + torch.exp(pick[..., 2].clamp(*FRAC_LOG_STD)) * eps[..., 0])
    frac = frac.clamp(1e-3, 1 - 1e-3)
    base = _speed_base(obs.need_v, psi)
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
    k_max = int(k.max().item()) if b else 0
    table = SplitTable(snaps.psi[:, 2], snaps.psi[:, 3], max(k_max - 1, 0), snaps.length_m, n)
    for step in range(k_max):
        active = k > step
        remaining = (k - step).clamp(min=0)
        anchor = torch.rand(b, generator=gen) * snaps.length_m
        obs = observe(
            arc, speed, present, hidden & present, remaining, psi, snaps.length_m, anchor, table
        )
        prop = propose(net, obs, psi, snaps.length_m, 1, gen)
        slot = _next_hidden_slot(hidden, present)
        onehot = torch.nn.functional.one_hot(slot, n).bool() & active[:, None]
        arc = torch.where(onehot, prop.arc[0][:, None], arc)
        speed = torch.where(onehot, prop.speed[0][:, None], speed)
        present = present | onehot
        log_p = log_p + torch.where(active, prop.log_prob_choice[0], torch.zeros_like(log_p))
    return arc, speed, hidden, log_p


# --------------------------------------------------------------------------- inference


def _logit(p: np.ndarray) -> np.ndarray:
    return np.log(p) - np.log1p(-p)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _log_softmax(x: np.ndarray) -> np.ndarray:
    top = x.max(axis=-1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    return x - top - np.log(np.exp(x - top).sum(axis=-1, keepdims=True))


def _categorical(log_w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(..., S) draws from the categoricals exp(log_w) (..., C), unnormalised, by inverse
    CDF of the uniforms ``u`` (..., S). A row without mass draws 0."""
    top = log_w.max(axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        cdf = np.cumsum(np.exp(log_w - np.where(np.isfinite(top), top, 0.0)), axis=-1)
        cdf /= cdf[..., -1:]
    return (u[..., None] >= cdf[..., None, :]).sum(axis=-1)


class FeasibleSplits:
    """Each gap's feasible split points in units of its position proposal (a standard
    normal z with fraction = sigmoid(mu + sigma z)), as disjoint pieces (B, N, P).

    The look-ahead's intervals (one per count pair, overlapping) are sorted and cut into
    disjoint pieces; each piece's probability and the inverse CDF within it are computed
    from log Phi (the lower tail, mirrored for pieces above the mean), so a piece far in
    the tail keeps an exact, tiny mass and its draws stay inside it.
    """

    def __init__(self, look: Lookahead, mu: np.ndarray, sigma: np.ndarray) -> None:
        tol = GEOMETRY_TOL_M
        order = np.argsort(np.where(look.ok, look.lo, np.inf), axis=-1)
        lo = np.take_along_axis(np.where(look.ok, look.lo - tol, np.inf), order, axis=-1)
        hi = np.take_along_axis(
            np.where(look.ok, np.maximum(look.hi, look.lo) + tol, -np.inf), order, axis=-1
        )
        covered = np.maximum.accumulate(hi, axis=-1)
        prev = np.concatenate([np.full_like(hi[..., :1], -np.inf), covered[..., :-1]], axis=-1)
        lo, hi = np.maximum(lo, prev), np.maximum(hi, prev)
        g = look.gap[..., None]
        good = hi > lo
        self.lo_m = np.where(good, lo, 0.25 * g)  # [m] from the gap's follower
        self.hi_m = np.where(good, hi, 0.75 * g)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            za = (_logit(self.lo_m / g) - mu[..., None]) / sigma[..., None]
            zb = (_logit(self.hi_m / g) - mu[..., None]) / sigma[..., None]
            self.flip = za > 0
            self.za = np.where(self.flip, -zb, za)  # lower end, <= 0
            self.zb = np.where(self.flip, -za, zb)
            self.log_phi_a, self.log_phi_b = log_ndtr(self.za), log_ndtr(self.zb)
            lm = self.log_phi_b + np.log(-np.expm1(self.log_phi_a - self.log_phi_b))
            self.log_mass = np.where(good & ~np.isnan(lm), lm, -np.inf)  # (B, N, P)
            # (B, N): log of the mass the gap's position proposal puts on feasible points.
            log_m = np.logaddexp.reduce(self.log_mass, axis=-1)
        self.log_m = np.where(
            look.empty[:, None], np.where(look.empty_ok, 0.0, -np.inf)[:, None], log_m
        )

    def sample(
        self,
        choice: np.ndarray,
        u_piece: np.ndarray,
        u: np.ndarray,
        mu: np.ndarray,
        sigma: np.ndarray,
        gap: np.ndarray,
    ) -> np.ndarray:
        """(B, S) split points [m] in gaps ``choice`` drawn from the truncated proposal
        (``mu``, ``sigma``, ``gap`` of the chosen gaps, (B, S)): a piece by its mass, then
        the inverse CDF within it."""
        rows = np.arange(len(choice))[:, None]
        piece = _categorical(self.log_mass[rows, choice], u_piece[..., None])[..., 0]
        idx = (rows, choice, piece)
        with np.errstate(divide="ignore"):
            # Phi(z) = (1 - u) Phi(za) + u Phi(zb), in logs.
            log_t = np.logaddexp(
                np.log1p(-u) + self.log_phi_a[idx], np.log(u) + self.log_phi_b[idx]
            )
        z = np.clip(ndtri_exp(log_t), self.za[idx], self.zb[idx])
        z = np.where(self.flip[idx], -z, z)
        return np.clip(gap * _sigmoid(mu + sigma * z), self.lo_m[idx], self.hi_m[idx])


@dataclass
class Completion:
    arc_m: np.ndarray
    speed_mps: np.ndarray
    projected: np.ndarray  # (B,) number of hidden vehicles that needed projection
    wall_s: float
    # (B, K_max) per step, the probability that one trial of the plain (untruncated)
    # proposal passes the check; NaN where the snapshot had no vehicle left to place.
    accept_prob: np.ndarray | None = None


def complete(
    net: GeneratorNet, snaps: Snapshots, t_max: int, seed: int, truncate: bool = True
) -> Completion:
    """Algorithm 3, batched: rejection sampling against Psi's bounds, projection as fallback.

    ``truncate`` draws each trial from the proposal restricted to the feasible split points
    (the T_max -> infinity limit of rejection; module docstring); False is the plain
    algorithm.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(int(seed))
    hidden = np.asarray(snaps.hidden, dtype=bool)
    present = ~hidden
    # Geometry in float64 (the network sees float32 features): accepted gaps are then
    # within Psi's bounds to rounding, not to float32's ~1e-4 m on a ring.
    arc = np.where(hidden, 0.0, snaps.arc_m).astype(np.float64)
    speed = np.where(hidden, 0.0, snaps.speed_mps).astype(np.float64)
    psi = PsiTensors.arrays(snaps)
    length = snaps.length_m
    b, n = arc.shape
    k = hidden.sum(axis=1)
    k_max = int(k.max()) if b else 0
    table = SplitTable(psi.d_min, psi.d_max, max(k_max - 1, 0), length, n)
    projected = np.zeros(b, dtype=int)
    accept_prob = np.full((b, k_max), np.nan)
    rank = np.where(hidden, hidden.cumsum(axis=1), 0)  # hidden slots fill in slot order
    rows = np.arange(b)
    for step in range(k_max):
        active = k > step
        remaining = np.maximum(k - step, 0)
        anchor = rng.random(b) * length
        obs = observe(arc, speed, present, hidden & present, remaining, psi, length, anchor, table)
        _, _, gap, valid, start = obs.geometry
        look = obs.look
        out = net.forward_numpy(obs.gap_feat, obs.glob).astype(np.float64)
        choosable = valid & (look.allowed | ~(look.allowed & valid).any(axis=1, keepdims=True))
        log_p = _log_softmax(np.where(choosable, out[..., 0], -np.inf))
        mu = out[..., 1]
        sigma = np.exp(np.clip(out[..., 2], *FRAC_LOG_STD))
        splits = FeasibleSplits(look, mu, sigma)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_acc = np.logaddexp.reduce(log_p + splits.log_m, axis=1)
        accept_prob[:, step] = np.where(active, np.exp(log_acc), np.nan)
        # Trials: the gap, the split point (truncated or plain) and the speed.
        trunc = truncate & np.isfinite(log_acc) & ~look.empty
        log_w = log_p
        u = rng.random((b, t_max, 3))
        eps = rng.standard_normal((b, t_max, 2))
        choice = _categorical(log_w, u[..., 0])  # (B, S)
        g, mu_c, sig_c = (np.take_along_axis(x, choice, axis=1) for x in (gap, mu, sigma))
        frac = np.clip(_sigmoid(mu_c + sig_c * eps[..., 0]), 1e-3, 1 - 1e-3)
        a1 = frac * g
        if trunc.any():
            a_t = splits.sample(choice, u[..., 1], u[..., 2], mu_c, sig_c, g)
            a1 = np.where(trunc[:, None], a_t, a1)
        base = _speed_base(obs.need_v, psi)[:, None]
        out_c = np.take_along_axis(out, choice[..., None], axis=1)  # (B, S, 5)
        log_std_v = np.clip(out_c[..., 4], *SPEED_LOG_STD)
        v_u = _sigmoid(base + out_c[..., 3] + np.exp(log_std_v) * eps[..., 1])
        v = np.minimum(psi.v_min[:, None] + psi.v_range[:, None] * v_u, psi.v_max[:, None])
        ok = look.accepts(choice, a1) & (v >= psi.v_min[:, None]) & (v <= psi.v_max[:, None])
        any_ok = ok.any(axis=1)
        # The first accepted candidate, else the last one, projected: the nearest split
        # point of its gap that passes, its speed clipped to the bounds.
        pick = np.where(any_ok, ok.argmax(axis=1), t_max - 1)
        c, a, new_v = choice[rows, pick], a1[rows, pick], v[rows, pick]
        if not any_ok.all():
            a = np.where(any_ok, a, look.project(c, a))
            new_v = np.where(any_ok, new_v, np.clip(new_v, psi.v_min, psi.v_max))
            projected += active & ~any_ok
        new_arc = (start[rows, c] + a) % length
        onehot = rank == step + 1
        arc = np.where(onehot, new_arc[:, None], arc)
        speed = np.where(onehot, new_v[:, None], speed)
        present = present | onehot
    # Observed vehicles never move: the input values, bit for bit.
    arc_out = np.where(snaps.hidden, arc % length, snaps.arc_m)
    speed_out = np.where(snaps.hidden, speed, snaps.speed_mps)
    return Completion(arc_out, speed_out, projected, time.perf_counter() - t0, accept_prob)


def rejection_success(comp: Completion, t_max: int) -> np.ndarray:
    """(B,) the probability that the plain Algorithm 3 (T_max untruncated trials per step)
    would have placed every vehicle of this completion's path without projection."""
    p = np.nan_to_num(comp.accept_prob, nan=1.0)
    return np.prod(1.0 - (1.0 - p) ** t_max, axis=1)


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

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

Extension (``complete(..., truncate=True)``, the default): the split point of each trial
is drawn from the position proposal truncated to the chosen gap's feasible split points,
the T_max -> infinity limit of resampling it (inverse CDF over the disjoint feasible
pieces, in log space so that any tail is exact). The gap is chosen as in the plain
algorithm, from the network's scores over the gaps with some feasible split point (the
same limit for the discrete part). Why: the paper's loss barely penalises a gap a few
metres past d_min or d_max (L_min, L_max are squared relative violations), so the trained
position spread collapses onto points just outside the bounds and the T_max trials are
nearly identical. The check still judges every candidate and projection stays the
counted fallback (a gap whose feasible pieces carry no mass at all under the proposal).
``truncate=False`` is the plain Algorithm 3. ``Completion.accept_prob`` keeps, per step,
the probability that one plain trial would have passed (sum_j p_j m_j, m_j the mass the
position proposal puts on gap j's feasible points), so how much the truncation does is
on record: ``rejection_success`` is the chance that plain Algorithm 3 would have placed
every vehicle of a completion without projection.

Extension (``generator.gap_choice = "posterior"``): the gap of the next vehicle is drawn
from the posterior of the vehicles' whereabouts under i.i.d. normal spacings with the
detectors' mean and std (``gap_posterior``), in training and inference alike; the network
then learns where in the gap and how fast. Trained on per-scene losses, the network's own
choice becomes deterministic (the gap that makes the loss smallest), which a real stream's
vehicles are not.

Inference runs in numpy (float64 geometry, the MLP in float32 with the trained weights):
placing one vehicle of one snapshot takes a few hundred tiny array operations, and
numpy's per-operation overhead is a third of torch's. Geometry and features are one
definition for both (``_xp``); training runs them in torch, with gradients, exactly as
before (same autograd graph, bit-identical weights).
"""

from __future__ import annotations

import functools
import math
import time
import weakref
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import pandas as pd
import torch
from numpy.lib.stride_tricks import sliding_window_view
from scipy.optimize import linear_sum_assignment
from scipy.special import log_ndtr, ndtri_exp
from torch import nn

from macromicro_sumo.data.objective import MacroTarget, macro_loss, macro_terms
from macromicro_sumo.data.ring import Snapshots

FEATURE_VERSION = 2
N_GAP_FEATURES = 7
N_GLOBAL_FEATURES = 9
LOSS_TERMS = ("L_speed", "L_mean", "L_min", "L_max", "L_var")
# Limits of the log-std of the position and speed heads.
FRAC_LOG_STD = (-5.0, 2.0)
SPEED_LOG_STD = (-6.0, 1.0)


def _xp(x: Any) -> Any:
    """The array module of ``x``: geometry and features run on torch (training, with
    gradients) and numpy (inference) from one definition."""
    return torch if isinstance(x, torch.Tensor) else np


def _take(x: Any, idx: Any) -> Any:
    """x[b, idx[b, i]] along axis 1 (numpy: trailing axes of x are kept)."""
    if isinstance(x, torch.Tensor):
        return x.gather(1, idx)
    return x[_rows(len(x)), idx]


@functools.lru_cache(maxsize=32)
def _rows(b: int, ndim: int = 2) -> np.ndarray:
    """np.arange(b) shaped (B, 1, ...) with ``ndim`` axes, for fancy indexing."""
    return np.arange(b).reshape(b, *[1] * (ndim - 1))


def _clip(x: Any, lo: Any = None, hi: Any = None) -> Any:
    """torch.clamp / np.clip without the latter's per-call overhead."""
    if isinstance(x, torch.Tensor):
        return torch.clamp(x, lo, hi)
    if lo is not None:
        x = np.maximum(x, lo)
    return x if hi is None else np.minimum(x, hi)


def _stack(xs: list[Any]) -> Any:
    """Stack along a new last axis."""
    if isinstance(xs[0], torch.Tensor):
        return torch.stack(xs, -1)
    a = np.array(xs, dtype=np.float64)  # the arrays must have the same shape
    return a.transpose(*range(1, a.ndim), 0)


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
        return _clip(0.5 * (self.v_max - self.v_min), 0.1)

    @cached_property
    def static_features(self) -> list[Any]:
        """The 5 global features (B,) each that depend on Psi alone (computed once):
        d_min, d_max relative to the mean spacing, then the speed range and centre, and the
        dispersion target (0 unless spacing_dispersion = "measured")."""
        xp = _xp(self.d_mean)
        d_std = xp.zeros_like(self.d_mean) if self.d_std is None else self.d_std
        return [
            self.d_min / self.d_mean,
            self.d_max / self.d_mean,
            (self.v_max - self.v_min) / self.v_mean,
            (self.v_min + self.v_max - 2 * self.v_mean) / (2 * self.v_scale),
            d_std / self.d_mean,
        ]

    @cached_property
    def columns(self) -> tuple[Any, ...]:
        """(v_scale, v_mean, d_mean, d_min, d_max) as (B, 1) columns (computed once)."""
        return tuple(
            x[:, None] for x in (self.v_scale, self.v_mean, self.d_mean, self.d_min, self.d_max)
        )


def scene_gaps(arc: Any, present: Any, length_m: float, anchor: Any) -> tuple[Any, ...]:
    """``ring_gaps`` of a scene, plus each gap's start [m] (B, N).

    An empty ring gets one virtual vehicle at ``anchor`` (a random angle) whose gap is the
    whole ring, so the first vehicle of a scene goes anywhere (rotation symmetry).
    """
    xp = _xp(arc)
    empty = ~present.any(1)
    # numpy skips it when no ring is empty; torch always takes it, so that the autograd
    # graph, and with it training, stays the same to the last bit.
    if xp is torch or empty.any():
        virtual = empty[:, None] & (xp.arange(arc.shape[1]) == 0)
        arc, present = xp.where(virtual, anchor[:, None], arc), present | virtual
    follower, leader, gap, valid = ring_gaps(arc, present, length_m)
    return follower, leader, gap, valid, _take(arc, follower)


# --------------------------------------------------------------------------- look-ahead

# Inference runs its geometry in float64; this absorbs its rounding, far below the 1e-6 m
# that metrics allow, and is the same for counts and split points so the two agree.
GEOMETRY_TOL_M = 1e-9


def _piece_range(x: np.ndarray, d_min: np.ndarray, d_max: np.ndarray) -> tuple[np.ndarray, ...]:
    """Fewest and most further vehicles m such that x splits into m + 1 gaps in [d_min, d_max]."""
    lo_m = np.maximum(np.ceil((x - GEOMETRY_TOL_M) / d_max) - 1, 0)
    hi_m = np.floor((x + GEOMETRY_TOL_M) / d_min) - 1
    return lo_m, hi_m


def _windows(x: np.ndarray) -> np.ndarray:
    """(..., R + 1, R + 1) of polynomials' coefficients x (..., R + 1) of degree 0..R: row c
    holds (x_{c - R}, ..., x_c), zero below degree 0; a strided view of x behind R zeros."""
    r1 = x.shape[-1]
    padded = np.concatenate([np.zeros((*x.shape[:-1], r1 - 1)), x], axis=-1)
    return sliding_window_view(padded, r1, axis=-1)


def _poly_mul(windows: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Products x y of polynomials truncated at degree R, O(R^2) each, given x's
    ``_windows``: coefficient c is row c of them times y reversed."""
    return (windows @ y[..., ::-1, None])[..., 0]


def _leave_one_out(p: np.ndarray, sets: bool = False) -> np.ndarray:
    """(B, N, R + 1): for every j, the product of the polynomials p[:, i] (B, N, R + 1) of
    all i but j, truncated at degree R.

    Prefix and suffix products (pre_j = p_0 ... p_{j-1}, suf_j = p_{j+1} ... p_{N-1}) give
    every j's product as pre_j suf_j: 3N products in all, where multiplying out each j's
    N - 1 others takes N^2 (the cost per step then grew with the square of the vehicles).
    Truncation commutes with the products, so the result is the same polynomial.
    ``sets``: p holds count sets as 0/1 coefficients (which totals a gap can take) and
    every product is clipped back to 0/1 (which totals the gaps can take together).
    """
    b, n, r1 = p.shape
    # One array runs both chains: [0, :, i] = pre_i, [1, :, i] = suf_{N-1-i}.
    factors = _windows(np.stack([p, p[:, ::-1]]))
    chain = np.zeros((2, b, n, r1))
    chain[:, :, 0, 0] = 1.0
    for i in range(n - 1):
        nxt = _poly_mul(factors[:, :, i], chain[:, :, i])
        chain[:, :, i + 1] = np.minimum(nxt, 1.0) if sets else nxt
    out = _poly_mul(_windows(chain[0]), chain[1, :, ::-1])
    return np.minimum(out, 1.0) if sets else out


@functools.lru_cache(maxsize=64)
def _count_pairs(r_max: int) -> tuple[np.ndarray, ...]:
    """(c1, c2, c1 + c2, counts 0..R) for ``SplitTable``."""
    pairs = np.array([(c1, t - c1) for t in range(r_max + 1) for c1 in range(t + 1)], float)
    c1, c2 = pairs.reshape(-1, 2).T
    return c1, c2, (c1 + c2).astype(int), np.arange(r_max + 1)


class SplitTable:
    """What the look-ahead needs that stays the same over the steps of one completion.

    Pairs (c1, c2) count the vehicles still to come behind and ahead of the next one in
    its gap, ordered by c1 + c2 so that the pairs for r vehicles to come are a prefix.
    A split point a1 (distance from the gap's follower) serves (c1, c2) if
    (c1 + 1) d_min <= a1 <= (c1 + 1) d_max and (c2 + 1) d_min <= gap - a1 <= (c2 + 1) d_max.
    """

    def __init__(self, d_min: np.ndarray, d_max: np.ndarray, r_max: int, length_m: float) -> None:
        d_min = np.asarray(d_min, dtype=np.float64)
        d_max = np.asarray(d_max, dtype=np.float64)
        c1, c2, self.total, self.counts = _count_pairs(r_max)
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

    @cached_property
    def allowed(self) -> np.ndarray:
        """(B, N) gaps with some feasible split point: rejecting the others up front is the
        T_max -> infinity limit of rejection for the discrete part of the proposal."""
        return np.logical_or.reduce(self.ok, axis=2) | self.empty[:, None]

    def accepts(self, choice: np.ndarray, a1: np.ndarray) -> np.ndarray:
        """(B, S) whether candidates (gap ``choice``, split point ``a1``) pass the check."""
        rows = _rows(len(choice))
        lo, hi, ok = self.lo[rows, choice], self.hi[rows, choice], self.ok[rows, choice]
        a = a1[..., None]
        inside = np.logical_or.reduce(
            ok & (a >= lo - GEOMETRY_TOL_M) & (a <= hi + GEOMETRY_TOL_M), axis=-1
        )
        return inside | (self.empty & self.empty_ok)[:, None]

    def project(self, choice: np.ndarray, a1: np.ndarray) -> np.ndarray:
        """(B,) the feasible split point of gap ``choice`` nearest to ``a1`` (a1 if none)."""
        rows = np.arange(len(choice))
        lo, hi, ok = self.lo[rows, choice], self.hi[rows, choice], self.ok[rows, choice]
        near = np.minimum(np.maximum(a1[:, None], lo), hi)
        dist = np.where(ok, np.abs(near - a1[:, None]), np.inf)
        best = near[rows, dist.argmin(axis=1)]
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
    sets (a small dynamic programme over 0..R), for every gap at once from prefix and
    suffix sumsets (``_leave_one_out``: linear in the number of gaps).
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
        # Valid gaps come first (arc order); the slots beyond can take {0} only.
        m = max(int(np.add.reduce(valid, axis=1).max()) if b else 0, 1)
        rest = _leave_one_out(sets[:, :m].astype(np.float64), sets=True) > 0
        if m < n:  # an invalid slot j: every valid gap absorbs
            every = _poly_mul(_windows(rest[:, :1].astype(np.float64)), sets[:, :1])
            rest = np.concatenate([rest, np.repeat(every > 0, n - m, axis=1)], axis=1)
    need = rem_after[:, None] - table.total[:n_pairs]  # (B, P): what the other gaps absorb
    ok = (need >= 0)[:, None, :] & rest[_rows(b, 3), _rows(n), np.maximum(need, 0)[:, None, :]]
    g = gap[..., None]
    lo = np.maximum(table.lo1[..., :n_pairs], g - table.lo2[..., :n_pairs])
    hi = np.minimum(table.hi1[..., :n_pairs], g - table.hi2[..., :n_pairs])
    ok = ok & valid[..., None] & (lo <= hi + 2 * GEOMETRY_TOL_M)
    empty_ok = (table.ring_lo <= rem_after) & (rem_after <= table.ring_hi)
    empty = ~np.logical_or.reduce(present, axis=1)
    return Lookahead(lo, hi, ok, empty, empty_ok, gap)


# --------------------------------------------------------------------------- gap posterior


@functools.lru_cache(maxsize=16)
def _gap_index(n: int) -> np.ndarray:
    """np.arange(n) shaped (N, 1), for fancy indexing."""
    return np.arange(n)[:, None]


def _next_gap_log_prob(log_w: np.ndarray, remaining: np.ndarray) -> np.ndarray:
    """(B, N) log P(a random one of the ``remaining`` vehicles lies in gap j) = log E[c_j] / R.

    ``log_w`` (B, N, R + 1): each gap's log-weight for holding c = 0..R of them; an
    allocation's weight is the product over gaps, restricted to sum(c) = remaining. For
    every j at once, the other gaps' joint weights are the product of their polynomials
    (sum_c w_i(c) x^c, truncated at degree R), from prefix and suffix products
    (``_leave_one_out``: O(N R^2) per row). Each gap's weights are scaled to a largest of 1
    first, so the products stay in range in linear space; a row whose allocations all
    vanish comes out NaN (no mass).
    """
    b, n, r1 = log_w.shape
    counts = np.arange(r1)
    top = np.maximum.reduce(log_w, axis=-1, keepdims=True)
    w = np.exp(log_w - np.where(top > -np.inf, top, 0.0))
    others = _leave_one_out(w)
    rest = remaining[:, None] - counts  # (B, R + 1): what the other gaps hold
    o = others[_rows(b, 3), _gap_index(n), np.maximum(rest, 0)[:, None, :]]
    use = ((rest >= 0) & (counts >= 1))[:, None, :]
    e = np.add.reduce(np.where(use, counts * w * o, 0.0), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(e / np.add.reduce(e, axis=1, keepdims=True))


def gap_posterior(
    gap: np.ndarray, valid: np.ndarray, remaining: np.ndarray, psi: PsiTensors
) -> np.ndarray:
    """(B, N) log-probability that the next hidden vehicle goes into each gap
    (``generator.gap_choice = "posterior"``).

    The posterior of the hidden vehicles' whereabouts under the simplest model the macro
    data define: spacings independent, normal with the detectors' mean spacing and spacing
    std (numpy ``psi``). A gap of length g holding c more vehicles has weight
    N(g; (c + 1) mu, (c + 1) s^2) / N(g; mu, s^2) against holding none, and the next
    vehicle goes into gap j with probability E[c_j] / (vehicles still to place). Gaps
    where no split point is feasible are then removed by the look-ahead, as from the
    network's scores. Why: a network trained on per-scene losses learns a deterministic
    choice (with one hidden vehicle, the largest gap in 99% of held-out scenes, where it
    lies in 96%; this posterior gives it 96.3% on average), so completed scenes lose the
    spread that the choice itself carries.
    """
    b, n = gap.shape
    r_max = max(int(remaining.max()) if b else 0, 1)
    counts = np.arange(r_max + 1)
    # Valid gaps come first (arc order): the slots beyond hold none and multiply by 1.
    m = max(int(np.add.reduce(valid, axis=1).max()) if b else 0, 1)
    gap, valid = gap[:, :m], valid[:, :m]
    # log N(g; (c + 1) mu, (c + 1) s^2) - log N(g; mu, s^2), with z = (g - mu) / s:
    z = ((gap - psi.d_mean[:, None]) / psi.d_std[:, None])[..., None]
    c_z = (counts * psi.d_mean[:, None] / psi.d_std[:, None])[:, None, :]
    log_w = 0.5 * (z * z - (z - c_z) ** 2 / (counts + 1) - np.log(counts + 1))
    log_w = np.where(valid[..., None], log_w, np.where(counts == 0, 0.0, -np.inf))
    out = _next_gap_log_prob(log_w, remaining)
    # A row with nothing to place (or no mass at all) keeps a uniform choice of its gaps.
    full = np.full((b, n), -np.inf)
    full[:, :m] = np.where(
        np.logical_or.reduce(np.isfinite(out), axis=1, keepdims=True),
        out,
        np.where(valid, 0.0, -np.inf),
    )
    return full


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
    xp = _xp(arc)
    n = arc.shape[1]
    m = present.sum(1)
    empty = m == 0
    follower, leader, gap, _, _ = geometry
    vs, vm, dm, d_min, d_max = psi.columns
    # Speeds enter the features detached: otherwise training uses a generated vehicle's
    # speed as a side channel to steer later placements (L_dist), pulling speeds away from
    # Psi's mean. A speed reaches the loss only through L_speed (and the speed centring).
    speed_in = speed.detach() if hasattr(speed, "detach") else speed
    v_f = xp.where(empty[:, None], vm, _take(speed_in, follower))
    v_l = xp.where(empty[:, None], vm, _take(speed_in, leader))
    gap_dm = gap / dm
    gap_feat = _stack(
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
    need_v = (n * psi.v_mean - v_sum) / _clip(remaining, 1)
    need_in = (n * psi.v_mean - v_sum_in) / _clip(remaining, 1)
    mean_v = xp.where(empty, psi.v_mean, v_sum_in / _clip(m, 1))
    d_min_rel, d_max_rel, *v_static = psi.static_features
    glob = _stack(
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


def _speed_base(need_v: Any, psi: PsiTensors) -> Any:
    """Logit of the speed the remaining vehicles need, on Psi's [v_min, v_max].

    Speeds live in Psi's [v_min, v_max] by construction (logit-normal on that interval):
    the paper's loss has no speed-bound term, so an unbounded proposal drifts outside.
    Centred on the speed the remaining vehicles need for Psi's mean: the MLP adds a residual.
    """
    need = _clip((need_v - psi.v_min) / _clip(psi.v_range, 1e-3), 0.02, 0.98)
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


# --------------------------------------------------------------------------- inference


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _log_softmax(x: np.ndarray) -> np.ndarray:
    top = np.maximum.reduce(x, axis=-1, keepdims=True)
    return x - top - np.log(np.add.reduce(np.exp(x - top), axis=-1, keepdims=True))


def _categorical(log_w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(..., S) draws from the categoricals exp(log_w) (..., C), unnormalised, by inverse
    CDF of the uniforms ``u`` (..., S). A row without mass draws 0."""
    cdf = np.cumsum(np.exp(log_w - np.maximum.reduce(log_w, axis=-1, keepdims=True)), axis=-1)
    cdf /= cdf[..., -1:]
    return np.add.reduce(u[..., None] >= cdf[..., None, :], axis=-1)


class FeasibleSplits:
    """Each gap's feasible split points in units of its position proposal (a standard
    normal z with fraction = sigmoid(mu + sigma z)), as disjoint pieces (B, N, P).

    The look-ahead's intervals (one per count pair, overlapping) are sorted and cut into
    disjoint pieces; each piece's probability and the inverse CDF within it are computed
    from log Phi (the lower tail, mirrored for pieces above the mean), so a piece far in
    the tail keeps an exact, tiny mass and its draws stay inside it. The intervals are
    widened by the check's tolerance, so a gap that fits exactly keeps a feasible piece.
    """

    def __init__(self, look: Lookahead, mu: np.ndarray, sigma: np.ndarray) -> None:
        tol = GEOMETRY_TOL_M
        lo = np.where(look.ok, look.lo - tol, np.inf)
        hi = np.where(look.ok, look.hi + tol, -np.inf)
        b, n, _ = lo.shape
        ix = (_rows(b, 3), _rows(n), lo.argsort(axis=-1))
        lo, hi = lo[ix], np.maximum.accumulate(hi[ix], axis=-1)
        # Sorted by start, piece i keeps what pieces before it do not cover.
        lo[..., 1:] = np.maximum(lo[..., 1:], hi[..., :-1])
        good = hi > lo
        g = look.gap[..., None]
        ends = np.array([np.where(good, lo, 0.25 * g), np.where(good, hi, 0.75 * g)])  # [m]
        z = (np.log(ends) - np.log(g - ends) - mu[..., None]) / sigma[..., None]
        flip = z[0] > 0
        z = np.where(flip, -z[::-1], z)  # mirrored above the mean: z[0] <= 0
        log_phi = log_ndtr(z)
        lm = log_phi[1] + np.log(-np.expm1(log_phi[0] - log_phi[1]))
        self.log_mass = np.where(good & (lm == lm), lm, -np.inf)  # (B, N, P)
        # What ``sample`` looks up for a chosen piece, in one array: log Phi at both ends,
        # both ends (mirrored or not), whether mirrored, both ends in metres.
        self.pieces = np.concatenate([log_phi, z, flip[None], ends])
        # (B, N): log of the mass the gap's position proposal puts on feasible points.
        log_m = np.logaddexp.reduce(self.log_mass, axis=-1)
        # Each gap's pieces as a CDF (B, N, P), to draw a piece by its mass.
        self.cdf = np.cumsum(np.exp(self.log_mass - log_m[..., None]), axis=-1)
        self.cdf /= self.cdf[..., -1:]
        empty = np.where(look.empty_ok, 0.0, -np.inf)[:, None]
        self.log_m = np.where(look.empty[:, None], empty, log_m)

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
        the inverse CDF within it. Call under np.errstate (rows without mass give NaN)."""
        rows = _rows(len(choice))
        piece = np.add.reduce(u_piece[..., None] >= self.cdf[rows, choice], axis=-1)
        log_a, log_b, za, zb, flip, lo, hi = self.pieces[:, rows, choice, piece]
        # Phi(z) = (1 - u) Phi(za) + u Phi(zb), in logs.
        z = ndtri_exp(np.logaddexp(np.log1p(-u) + log_a, np.log(u) + log_b))
        z = np.minimum(np.maximum(z, za), zb)
        z = np.where(flip > 0, -z, z)
        return np.minimum(np.maximum(gap * _sigmoid(mu + sigma * z), lo), hi)


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
    # Geometry in float64 (the network sees float32 features): accepted gaps are then
    # within Psi's bounds to rounding, not to float32's ~1e-4 m on a ring.
    arc = np.where(hidden, 0.0, snaps.arc_m).astype(np.float64)
    speed = np.where(hidden, 0.0, snaps.speed_mps).astype(np.float64)
    psi = PsiTensors.arrays(snaps)
    b, n = arc.shape
    k = hidden.sum(axis=1)
    k_max = int(k.max()) if b else 0
    state = _Scene(arc, speed, ~hidden, hidden, snaps.length_m)
    table = SplitTable(psi.d_min, psi.d_max, max(k_max - 1, 0), snaps.length_m)
    weights = net.numpy_weights()
    projected = np.zeros(b, dtype=int)
    accept_prob = np.full((b, k_max), np.nan)
    rank = np.where(hidden, hidden.cumsum(axis=1), 0)  # hidden slots fill in slot order
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for step in range(k_max):
            active = k > step
            out = _algorithm3_step(net, weights, state, psi, table, k - step, t_max, truncate, rng)
            projected += active & out.projected
            accept_prob[:, step] = np.where(active, out.accept_prob, np.nan)
            state.place(rank == step + 1, out.arc, out.speed)
    # Observed vehicles never move: the input values, bit for bit.
    arc_out = np.where(hidden, state.arc % snaps.length_m, snaps.arc_m)
    speed_out = np.where(hidden, state.speed, snaps.speed_mps)
    return Completion(arc_out, speed_out, projected, time.perf_counter() - t0, accept_prob)


@dataclass
class _Scene:
    """A scene being completed (numpy, (B, N) each)."""

    arc: np.ndarray
    speed: np.ndarray
    present: np.ndarray
    hidden: np.ndarray
    length_m: float

    def place(self, onehot: np.ndarray, arc: np.ndarray, speed: np.ndarray) -> None:
        self.arc = np.where(onehot, arc[:, None], self.arc)
        self.speed = np.where(onehot, speed[:, None], self.speed)
        self.present = self.present | onehot


@dataclass
class _Placed:
    arc: np.ndarray  # (B,) [m]
    speed: np.ndarray  # (B,)
    projected: np.ndarray  # (B,) no trial passed: projected
    accept_prob: np.ndarray  # (B,) one plain trial's chance to pass


def _algorithm3_step(
    net: GeneratorNet,
    weights: tuple[np.ndarray, ...],
    scene: _Scene,
    psi: PsiTensors,
    table: SplitTable,
    remaining: np.ndarray,
    t_max: int,
    truncate: bool,
    rng: np.random.Generator,
) -> _Placed:
    """One vehicle for every scene: T_max trials, the first that passes, else projection."""
    b = len(remaining)
    rows = np.arange(b)
    remaining = np.maximum(remaining, 0)
    anchor = rng.random(b) * scene.length_m
    obs = observe(scene.arc, scene.speed, scene.present, remaining, psi, scene.length_m, anchor)
    _, _, gap, valid, start = obs.geometry
    look = lookahead(
        table,
        obs.geometry,
        scene.present,
        scene.hidden & scene.present,
        np.maximum(remaining - 1, 0),
    )
    out = net.forward_numpy(obs.gap_feat, obs.glob, weights).astype(np.float64)
    if net.gap_choice == "posterior":
        out[..., 0] = gap_posterior(gap, valid, remaining, psi)
    allowed = look.allowed & valid
    choosable = valid & (allowed | ~np.logical_or.reduce(allowed, axis=1, keepdims=True))
    log_p = _log_softmax(np.where(choosable, out[..., 0], -np.inf))
    mu = out[..., 1]
    sigma = np.exp(np.minimum(np.maximum(out[..., 2], FRAC_LOG_STD[0]), FRAC_LOG_STD[1]))
    splits = FeasibleSplits(look, mu, sigma)
    log_acc = np.logaddexp.reduce(log_p + splits.log_m, axis=1)
    # Trials: the gap, the split point (truncated or plain) and the speed.
    u = rng.random((3, b, t_max))
    eps = rng.standard_normal((2, b, t_max))
    choice = _categorical(log_p, u[0])  # (B, S)
    sel = (rows[:, None], choice)
    g, mu_c, sig_c, out_c = gap[sel], mu[sel], sigma[sel], out[sel]
    trunc = (log_acc > -np.inf) & ~look.empty if truncate else np.zeros(b, dtype=bool)
    if trunc.all():
        a1 = splits.sample(choice, u[1], u[2], mu_c, sig_c, g)
    else:
        a1 = g * np.minimum(np.maximum(_sigmoid(mu_c + sig_c * eps[0]), 1e-3), 1 - 1e-3)
        if trunc.any():
            a1 = np.where(trunc[:, None], splits.sample(choice, u[1], u[2], mu_c, sig_c, g), a1)
    v_min, v_max = psi.v_min[:, None], psi.v_max[:, None]
    log_std_v = np.minimum(np.maximum(out_c[..., 4], SPEED_LOG_STD[0]), SPEED_LOG_STD[1])
    v_u = _sigmoid(
        _speed_base(obs.need_v, psi)[:, None] + out_c[..., 3] + np.exp(log_std_v) * eps[1]
    )
    v = np.minimum(v_min + psi.v_range[:, None] * v_u, v_max)
    ok = look.accepts(choice, a1) & (v >= v_min) & (v <= v_max)
    any_ok = np.logical_or.reduce(ok, axis=1)
    # The first accepted candidate, else the last one, projected: the nearest split
    # point of its gap that passes, its speed clipped to the bounds.
    pick = np.where(any_ok, ok.argmax(axis=1), t_max - 1)
    c, a, new_v = choice[rows, pick], a1[rows, pick], v[rows, pick]
    if not any_ok.all():
        a = np.where(any_ok, a, look.project(c, a))
        new_v = np.where(any_ok, new_v, np.minimum(np.maximum(new_v, psi.v_min), psi.v_max))
    return _Placed((start[rows, c] + a) % scene.length_m, new_v, ~any_ok, np.exp(log_acc))


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

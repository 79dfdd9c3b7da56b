"""The ring generator's counting: the look-ahead of Algorithm 3 and the gap posterior.

Both sum over the ways the vehicles still to place can be shared out among the current
gaps, as products of truncated polynomials (one per gap, its coefficients over the count
it takes), for every gap at once from prefix and suffix products (``_leave_one_out``:
linear in the number of gaps). numpy only (the inference geometry, float64).

Look-ahead (``SplitTable``, ``lookahead``): a touched gap that will still receive
vehicles is judged by what it can hold: it must split into m + 1 gaps in [d_min, d_max]
for some m <= vehicles still to place (the paper's check when none remain; without it a
whole scene, K = N, could never start). ``Lookahead`` holds, per gap, the split points of
the next vehicle that keep the scene completable.

Extension (``generator.gap_choice = "posterior"``): the gap of the next vehicle is drawn
from the posterior of the vehicles' whereabouts under i.i.d. normal spacings with the
detectors' mean and std (``gap_posterior``), in training and inference alike; the network
then learns where in the gap and how fast. Trained on per-scene losses, the network's own
choice becomes deterministic (the gap that makes the loss smallest), which a real stream's
vehicles are not.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from macromicro_sumo.generator.ring_gaps import PsiTensors, row_index, take

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
        rows = row_index(len(choice))
        lo, hi, ok = self.lo[rows, choice], self.hi[rows, choice], self.ok[rows, choice]
        a = a1[..., None]
        inside = np.logical_or.reduce(
            ok & (a >= lo - GEOMETRY_TOL_M) & (a <= hi + GEOMETRY_TOL_M), axis=-1
        )
        return inside | (self.empty & self.empty_ok)[:, None]

    def project(self, choice: np.ndarray, a1: np.ndarray, standstill_m: float = 0.0) -> np.ndarray:
        """(B,) the feasible split point of gap ``choice`` nearest to ``a1``.

        With none (Psi's bounds cannot be met), ``a1`` itself, or with ``standstill_m`` > 0
        the point nearest to it that keeps both new spacings at least that long (the gap's
        middle where it cannot): Psi's spacing bounds, measured from passages at the
        detectors, can exclude every real gap of a dense ring (ring_sugiyama: 22% of the
        true spacings lie below the detectors' d_min), and a split point left where the
        proposal drew it put vehicles on top of each other.
        """
        rows = np.arange(len(choice))
        lo, hi, ok = self.lo[rows, choice], self.hi[rows, choice], self.ok[rows, choice]
        near = np.minimum(np.maximum(a1[:, None], lo), hi)
        dist = np.where(ok, np.abs(near - a1[:, None]), np.inf)
        best = near[rows, dist.argmin(axis=1)]
        fallback = a1
        if standstill_m > 0:
            g = self.gap[rows, choice]
            inner = np.minimum(np.maximum(a1, standstill_m), g - standstill_m)
            fallback = np.where(g >= 2 * standstill_m, inner, 0.5 * g)
        return np.where(ok.any(axis=1) & ~self.empty, best, np.where(self.empty, a1, fallback))


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
    touched = valid & (take(generated, follower) | take(generated, leader))
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
    ok = (need >= 0)[:, None, :] & rest[
        row_index(b, 3), row_index(n), np.maximum(need, 0)[:, None, :]
    ]
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
    o = others[row_index(b, 3), _gap_index(n), np.maximum(rest, 0)[:, None, :]]
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
    return spacing_posterior(gap, valid, remaining, psi.d_mean, psi.d_std)


def spacing_posterior(
    gap: np.ndarray,
    valid: np.ndarray,
    remaining: np.ndarray,
    d_mean: np.ndarray,
    d_std: np.ndarray,
) -> np.ndarray:
    """``gap_posterior`` on plain arrays: gaps (B, N) [m], valid gaps first in each row,
    ``remaining`` (B,) vehicles still to place, the spacings' mean and std (B,) [m]. The
    section generator calls it per closed one-lane scene (``section_model.propose``)."""
    b, n = gap.shape
    r_max = max(int(remaining.max()) if b else 0, 1)
    counts = np.arange(r_max + 1)
    # Valid gaps come first (arc order): the slots beyond hold none and multiply by 1.
    m = max(int(np.add.reduce(valid, axis=1).max()) if b else 0, 1)
    gap, valid = gap[:, :m], valid[:, :m]
    # log N(g; (c + 1) mu, (c + 1) s^2) - log N(g; mu, s^2), with z = (g - mu) / s:
    z = ((gap - d_mean[:, None]) / d_std[:, None])[..., None]
    c_z = (counts * d_mean[:, None] / d_std[:, None])[:, None, :]
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

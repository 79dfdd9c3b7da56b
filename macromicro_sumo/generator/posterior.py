"""The gap posterior of the hidden vehicles (``generator.gap_choice = "posterior"``).

The gap of the next hidden vehicle is drawn from the posterior of the vehicles' whereabouts
under i.i.d. normal spacings with the detectors' mean and std (``spacing_posterior``), in
training and inference alike; the network then learns where in the gap and how fast. Trained
on per-scene losses, the network's own choice becomes deterministic (the gap that makes the
loss smallest), which a real stream's vehicles are not.

It sums over the ways the vehicles still to place can be shared out among the current gaps,
as products of truncated polynomials (one per gap, its coefficients over the count it takes),
for every gap at once from prefix and suffix products (``_leave_one_out``: linear in the
number of gaps). numpy only (the inference geometry, float64).
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


def row_index(b: int, ndim: int = 2) -> np.ndarray:
    """np.arange(b) shaped (B, 1, ...) with ``ndim`` axes, for fancy indexing."""
    return np.arange(b).reshape(b, *[1] * (ndim - 1))


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


def _leave_one_out(p: np.ndarray) -> np.ndarray:
    """(B, N, R + 1): for every j, the product of the polynomials p[:, i] (B, N, R + 1) of
    all i but j, truncated at degree R.

    Prefix and suffix products (pre_j = p_0 ... p_{j-1}, suf_j = p_{j+1} ... p_{N-1}) give
    every j's product as pre_j suf_j: 3N products in all, where multiplying out each j's
    N - 1 others takes N^2 (the cost per step then grew with the square of the vehicles).
    Truncation commutes with the products, so the result is the same polynomial.
    """
    b, n, r1 = p.shape
    # One array runs both chains: [0, :, i] = pre_i, [1, :, i] = suf_{N-1-i}.
    factors = _windows(np.stack([p, p[:, ::-1]]))
    chain = np.zeros((2, b, n, r1))
    chain[:, :, 0, 0] = 1.0
    for i in range(n - 1):
        chain[:, :, i + 1] = _poly_mul(factors[:, :, i], chain[:, :, i])
    out = _poly_mul(_windows(chain[0]), chain[1, :, ::-1])
    return out


@functools.lru_cache(maxsize=64)
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


def spacing_posterior(
    gap: np.ndarray,
    valid: np.ndarray,
    remaining: np.ndarray,
    d_mean: np.ndarray,
    d_std: np.ndarray,
) -> np.ndarray:
    """(B, N) log-probability that the next hidden vehicle goes into each gap: gaps (B, N)
    [m], valid gaps first in each row, ``remaining`` (B,) vehicles still to place, the
    spacings' mean and std (B,) [m]. The section generator calls it per closed one-lane
    scene (``section_model.propose``).

    The posterior under the simplest model the macro data define: spacings independent,
    normal with the detectors' mean spacing and spacing std. A gap of length g holding c
    more vehicles has weight N(g; (c + 1) mu, (c + 1) s^2) / N(g; mu, s^2) against holding
    none, and the next vehicle goes into gap j with probability E[c_j] / (vehicles still to
    place). Why: a network trained on per-scene losses learns a deterministic choice (with
    one hidden vehicle, the largest gap in 99% of held-out scenes, where it lies in 96%;
    this posterior gives it 96.3% on average), so completed scenes lose the spread that the
    choice itself carries.
    """
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

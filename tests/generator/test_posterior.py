"""The gap posterior (``generator.gap_choice = "posterior"``) against brute force: every
allocation of the vehicles still to place, and the quadratic leave-one-out products that the
prefix/suffix products replaced (linear in the number of gaps)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from macromicro_sumo.generator.posterior import _leave_one_out, spacing_posterior

N = 5
MEAN_M, STD_M = 2 * np.pi * 100.0 / N, 30.0  # the paper ring's L / N, a 30 m spread


def test_gap_posterior_is_the_posterior_of_every_allocation():
    """E[c_j] / R over all allocations of R vehicles to the gaps, each weighted by the
    normal spacing likelihood (mean L / N, std 30 m) of the scene it makes."""
    rng = np.random.default_rng(1)
    b = 8
    gap = rng.uniform(80.0, 330.0, (b, N))
    valid = np.ones((b, N), bool)
    valid[0, 4] = valid[1, 3:] = False
    remaining = rng.integers(1, 4, b)
    mean, std = np.full(b, MEAN_M), np.full(b, STD_M)
    got = np.exp(spacing_posterior(gap, valid, remaining, mean, std))

    def log_n(x, m, v):
        return -0.5 * ((x - m) ** 2 / v + np.log(v))

    var = STD_M**2
    for i in range(b):
        e, z = np.zeros(N), 0.0
        for c in itertools.product(range(remaining[i] + 1), repeat=N):
            if sum(c) != remaining[i] or any(c[j] and not valid[i, j] for j in range(N)):
                continue
            w = np.exp(
                sum(
                    log_n(gap[i, j], (c[j] + 1) * MEAN_M, (c[j] + 1) * var)
                    - log_n(gap[i, j], MEAN_M, var)
                    for j in range(N)
                    if valid[i, j]
                )
            )
            e, z = e + w * np.array(c), z + w
        np.testing.assert_allclose(got[i], e / z / remaining[i], atol=1e-9, err_msg=str(i))
    assert (got[~valid] == 0).all()
    # Nothing left to place: a uniform choice of the valid gaps (the step is inactive).
    idle = np.exp(spacing_posterior(gap[:2], valid[:2], np.zeros(2, int), mean[:2], std[:2]))
    np.testing.assert_allclose(idle.sum(axis=1), valid[:2].sum(axis=1))


def quadratic_leave_one_out(p: np.ndarray) -> np.ndarray:
    """Every j's product of the others, multiplied out one polynomial at a time."""
    b, n, r1 = p.shape
    out = np.zeros((b, n, r1))
    out[..., 0] = 1.0
    for j in range(n):
        for i in range(n):
            if i != j:
                prod = np.zeros((b, r1))
                for d in range(r1):
                    prod[:, d:] += out[:, j, d : d + 1] * p[:, i, : r1 - d]
                out[:, j] = prod
    return out


@pytest.mark.parametrize("n", [1, 2, 3, 7, 22])
@pytest.mark.parametrize("r1", [1, 2, 6])
def test_leave_one_out_equals_multiplying_out_the_others(n, r1):
    rng = np.random.default_rng([n, r1])
    w = rng.uniform(0.0, 1.0, (4, n, r1)) * (rng.random((4, n, r1)) < 0.8)
    np.testing.assert_allclose(
        _leave_one_out(w), quadratic_leave_one_out(w), rtol=1e-13, atol=1e-300
    )

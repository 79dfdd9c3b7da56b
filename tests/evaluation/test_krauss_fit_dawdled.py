"""The Krauss-form prior's relaxation refitted next to SUMO's dawdled mean a where a falls
back (``evaluation.krauss_fit.fit_krauss``'s ``dawdle_sigma``, ``policy.relax_refit =
"dawdled"``). The pairs are SUMO's Krauss free-road update as numpy (``MSCFModel_Krauss``:
v' = min(v + a dt, V), less its dawdle sigma a dt U, U uniform; a = 2.6, sigma = 0.5): the
drivers accelerate at about a (1 - sigma / 2) = 1.95 m/s^2 up to their desired speed V and
cruise there. Each pair carries its driver's V as an estimate, 5% off (as the observed
drivers' ratios are: most are lower bounds), so cruising pairs favour a long relaxation.
Next to the undawdled 2.6 the refit lengthens it further, until (V - v) / T matches the
drivers below V (drawn arterial 1706's pairs: 3.43 s), next to 1.95 less (1706: 0.61 s)."""

from __future__ import annotations

import numpy as np
import pytest

from macromicro_sumo.evaluation.krauss_fit import (
    dawdled_mean_accel,
    fit_krauss,
    krauss_policy_accel,
    sumo_defaults,
)

DT_S, A, SIGMA = 0.5, 2.6, 0.5


def dawdling_pairs(seed: int = 3, drivers: int = 60, steps: int = 20, off: float = 0.05):
    """(obs, accel) of free drivers starting at rest, each with its own desired speed V in
    [11, 15] m/s, its estimate (V times 1 + ``off`` N(0, 1)) as its limit column (speed factor
    1), no leader; ``steps`` samples each (10 s: the pull-away and a few seconds' cruise)."""
    rng = np.random.default_rng(seed)
    obs, acc = [], []
    for top in rng.uniform(11.0, 15.0, drivers):
        seen = top * (1.0 + off * rng.standard_normal())
        v = 0.0
        for _ in range(steps):
            nxt = min(v + A * DT_S, top)
            nxt = max(0.0, nxt - SIGMA * min(A * DT_S, nxt) * rng.uniform())
            obs.append((v, seen, 1.0e5, 0.0))
            acc.append((nxt - v) / DT_S)
            v = nxt
    return np.array(obs), np.array(acc)


def deployed_free_accel(params, obs: np.ndarray, sigma: float) -> np.ndarray:
    """The prior's free acceleration as the deployment drives a fallen-back a with its command
    dawdle (``deploy.safety.dawdled_accel``, from v = a on): min(prior, a (1 - sigma / 2))."""
    prior = krauss_policy_accel(obs, params, 0.0, DT_S)
    return np.minimum(prior, dawdled_mean_accel(params.accel_mps2, sigma))


def test_the_relaxation_refitted_next_to_the_dawdled_mean_recovers_the_drivers_pull_away():
    obs, acc = dawdling_pairs()
    why = {"accel_mps2": "held at the vType's a (the test's fallback)"}
    vtype = fit_krauss(obs, acc, 0.0, DT_S, sumo_defaults(), why)
    dawdled = fit_krauss(obs, acc, 0.0, DT_S, sumo_defaults(), why, dawdle_sigma=SIGMA)
    # a keeps its fallback in both (the deployment's dawdle reads it); only relax_s differs
    assert vtype.params.accel_mps2 == dawdled.params.accel_mps2 == pytest.approx(A)
    assert "dawdled at sigma 0.5" in dawdled.refitted["relax_s"]
    assert "dawdled" not in vtype.refitted["relax_s"]
    assert dawdled.params.relax_s < vtype.params.relax_s - 0.2
    # between 0.5 and 0.85 of V the drivers pull away at ~1.95 m/s^2; the deployed prior
    # with the dawdled refit does too (1.87), with the undawdled one it tapers (1.78)
    band = (obs[:, 0] > 0.5 * obs[:, 1]) & (obs[:, 0] < 0.85 * obs[:, 1])
    truth = acc[band].mean()
    assert truth == pytest.approx(dawdled_mean_accel(A, SIGMA), abs=0.1)
    near = deployed_free_accel(dawdled.params, obs[band], SIGMA).mean()
    far = deployed_free_accel(vtype.params, obs[band], SIGMA).mean()
    assert abs(near - truth) < 0.1 < 0.15 < truth - far


def test_without_a_fallback_or_without_dawdle_the_fit_is_unchanged():
    obs, acc = dawdling_pairs(seed=4, drivers=30, off=0.0)
    plain = fit_krauss(obs, acc, 0.0, DT_S, sumo_defaults())
    again = fit_krauss(obs, acc, 0.0, DT_S, sumo_defaults(), dawdle_sigma=SIGMA)
    if "accel_mps2" not in plain.fallback:  # a fitted: sigma is not read
        assert again == plain
    zero = fit_krauss(obs, acc, 0.0, DT_S, sumo_defaults(), {"accel_mps2": "x"}, dawdle_sigma=0.0)
    one = fit_krauss(obs, acc, 0.0, DT_S, sumo_defaults(), {"accel_mps2": "x"})
    assert zero == one
    assert dawdled_mean_accel(2.6, 0.5) == pytest.approx(1.95)

"""Per-driver following (``evaluation.driver_follow``): each driver's tau recovered from its
own following pairs, their distribution, and seeded draws of it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from macromicro_sumo.env.driver_tau import driver_tau_levels, slot_tau_levels, taus_at
from macromicro_sumo.evaluation.driver_follow import (
    MIN_DRIVER_TAUS,
    driver_taus,
    krauss_accel_per_driver,
    tau_quantiles,
)
from macromicro_sumo.evaluation.krauss_fit import KraussParams, krauss_policy_accel

LENGTH_M, DT_S = 5.0, 0.5
# The pooled fit's other parameters (502's: a at SUMO's default, relaxation 10 s).
POOLED = KraussParams(1.0, 2.6, 4.05, 1.06, 2.7, 10.0)


def _following_pairs(
    rng: np.random.Generator, tau_s: float, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` pairs of a driver at ``tau_s`` following near its equilibrium gap on a 25 m/s
    road, accelerations with SUMO-like noise (0.3 m/s^2)."""
    v = rng.uniform(10.0, 24.0, n)
    gap = v * tau_s * rng.uniform(0.8, 1.4, n)
    obs = np.column_stack(
        [v, np.full(n, 25.0), gap + LENGTH_M + POOLED.min_gap_m, rng.normal(0.0, 1.0, n)]
    )
    truth = dataclasses.replace(POOLED, tau_s=tau_s)
    accel = krauss_policy_accel(obs, truth, LENGTH_M, DT_S) + rng.normal(0.0, 0.3, n)
    return obs, accel


def _two_types(seed: int = 0) -> tuple[np.ndarray, np.ndarray, list, dict]:
    """20 drivers at tau 1.0 s and 20 at 1.5 s (a Krauss and an IDM-like group), 150 pairs
    each: (obs, accel, the pairs' keys, each driver's tau)."""
    rng = np.random.default_rng(seed)
    obs, acc, keys, true = [], [], [], {}
    for i in range(40):
        key = (0, f"v{i}")
        true[key] = 1.0 if i % 2 else 1.5
        o, a = _following_pairs(rng, true[key], 150)
        obs.append(o)
        acc.append(a)
        keys += [key] * len(a)
    return np.concatenate(obs), np.concatenate(acc), keys, true


def test_each_drivers_tau_is_recovered_from_its_own_pairs() -> None:
    obs, acc, keys, true = _two_types()
    taus = driver_taus(obs, acc, keys, POOLED, LENGTH_M, DT_S)
    assert set(taus) == set(true)
    err = np.array([taus[k] - true[k] for k in true])
    assert np.abs(err).max() < 0.06, err
    q = tau_quantiles(list(taus.values()))
    assert q is not None
    # Two groups, not one tau between them: the quartiles sit on the two types.
    lo, hi = np.interp([0.25, 0.75], np.linspace(0.0, 1.0, len(q)), q)
    assert lo == pytest.approx(1.0, abs=0.06) and hi == pytest.approx(1.5, abs=0.06)


def test_a_driver_whose_safe_speed_never_binds_is_left_out() -> None:
    obs, acc, keys, _ = _two_types()
    far = obs[:150].copy()
    far[:, 2] = far[:, 0] * 1.9 + 9.0  # near by the free test, yet far beyond any tau
    far[:, 3] = 0.0
    # It accelerates towards its desired speed as if no one were ahead.
    far_acc = np.minimum(POOLED.accel_mps2, (25.0 - far[:, 0]) / POOLED.relax_s)
    taus = driver_taus(
        np.concatenate([obs, far]),
        np.concatenate([acc, far_acc]),
        [*keys, *[(1, "cruiser")] * 150],
        POOLED,
        LENGTH_M,
        DT_S,
    )
    assert (1, "cruiser") not in taus and len(taus) == 40


def test_a_tau_at_the_grids_edge_is_left_out() -> None:
    """A driver following at 4 s (beyond the searched taus) fits the grid's largest tau:
    that says only that its tau is at least that, so it gives none."""
    rng = np.random.default_rng(3)
    o, a = _following_pairs(rng, 1.2, 150)
    far_o, far_a = _following_pairs(rng, 4.0, 150)
    keys = [(0, "near")] * 150 + [(0, "far")] * 150
    far_o[:, 2] = np.minimum(far_o[:, 2], far_o[:, 0] * 1.99 + 9.0)  # near by the free test
    far_a = krauss_policy_accel(
        far_o, dataclasses.replace(POOLED, tau_s=4.0), LENGTH_M, DT_S
    ) + rng.normal(0.0, 0.3, 150)
    taus = driver_taus(
        np.concatenate([o, far_o]), np.concatenate([a, far_a]), keys, POOLED, LENGTH_M, DT_S
    )
    assert list(taus) == [(0, "near")]


def test_too_few_drivers_give_no_distribution() -> None:
    assert tau_quantiles([1.0] * (MIN_DRIVER_TAUS - 1)) is None
    assert tau_quantiles([1.0] * MIN_DRIVER_TAUS) is not None


def test_same_seed_same_draws() -> None:
    ids = [f"veh{i}" for i in range(200)]
    a = driver_tau_levels(7, 2, ids)
    assert np.array_equal(a, driver_tau_levels(7, 2, ids))
    # A driver's level is its own, in whatever order the drivers come.
    assert np.array_equal(driver_tau_levels(7, 2, ids[::-1]), a[::-1])
    assert not np.array_equal(a, driver_tau_levels(8, 2, ids))
    assert not np.array_equal(a, driver_tau_levels(7, 3, ids))
    s = slot_tau_levels(7, (4, 50))
    assert np.array_equal(s, slot_tau_levels(7, (4, 50)))
    assert not np.array_equal(s, slot_tau_levels(8, (4, 50)))
    _, _, _, true = _two_types()
    q = tau_quantiles(list(true.values()))
    assert q is not None
    drawn = taus_at(q, a)
    assert drawn.min() >= 1.0 and drawn.max() <= 1.5
    # About half of each type, as in the data.
    assert 0.35 < np.mean(drawn < 1.25) < 0.65


def test_per_driver_accel_is_each_rows_own_model() -> None:
    obs, _, _, _ = _two_types()
    rows = obs[:300:15]
    tau = np.linspace(0.8, 1.8, len(rows))
    got = krauss_accel_per_driver(rows, POOLED, tau, LENGTH_M, DT_S)
    one = [
        krauss_policy_accel(r[None], dataclasses.replace(POOLED, tau_s=t), LENGTH_M, DT_S)[0]
        for r, t in zip(rows, tau, strict=True)
    ]
    assert np.allclose(got, one)
    assert not np.allclose(got, krauss_policy_accel(rows, POOLED, LENGTH_M, DT_S))


def test_the_prior_record_has_the_observed_drivers_taus(tmp_path) -> None:
    """The Krauss prior's manifest record carries its observed drivers' own taus (real SUMO:
    game/ramp's main line, SUMO's Krauss cars at tau 1 s)."""
    from conftest import game_ramp_truth

    from macromicro_sumo.pipeline.build import fit_residual_prior

    sc, truth = game_ramp_truth(tmp_path, "drawn")
    prior, extra, _ = fit_residual_prior(sc, truth, truth.runs)
    taus = extra["prior"]["driver_taus"]
    assert taus["drivers"] >= MIN_DRIVER_TAUS
    q = taus["quantiles_s"]
    assert list(q) == ["0.05", "0.25", "0.5", "0.75", "0.95"]
    assert q["0.05"] <= q["0.5"] <= q["0.95"]
    assert 0.0 <= taus["share_at_or_below_prior"] <= 1.0
    assert q["0.5"] == pytest.approx(1.0, abs=0.25)  # SUMO's tau, the cars' own


def test_the_torch_prior_takes_a_tau_per_row() -> None:
    """The carrier's contract: the agent's Krauss prior (``policy.prior``) with a tau per
    row equals the numpy per-driver model (both in float64)."""
    import torch

    from macromicro_sumo.policy.prior import KRAUSS_PRIOR_KEYS, krauss_prior_accel

    obs, _, _, _ = _two_types()
    rows = obs[:300:15]
    tau = np.linspace(0.8, 1.8, len(rows))
    p = {**POOLED.as_dict(), "veh_length_m": LENGTH_M, "dt_s": DT_S}
    buf = {k: torch.tensor(float(p[k]), dtype=torch.float64) for k in KRAUSS_PRIOR_KEYS}
    buf["tau_s"] = torch.as_tensor(tau)
    got = krauss_prior_accel(torch.as_tensor(rows), buf).numpy()
    want = krauss_accel_per_driver(rows, POOLED, tau, LENGTH_M, DT_S)
    assert np.allclose(got, want)

"""Micro consistency scores a policy trained with the drivers' own taus
(``policy.driver_follow``, the agent's ``driver_tau`` buffer) on the held-out observed pairs
with each pair's driver's own tau as the observations' trailing column (``pair_taus``, as
the training's likelihood pairs take them: the driver's tau fitted on its record, else the
deployment's draw for it); a policy without the buffer with the prior's one tau, as before.
Real SUMO (tests/conftest.py's ``ring_driver_follow``) and real torch."""

from __future__ import annotations

import numpy as np
import torch

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS
from macromicro_sumo.env.driver_tau import DriverTaus, with_tau
from macromicro_sumo.env.observed_drivers import observed_drivers
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.evaluation.driver_follow import driver_taus, held_out_pairs
from macromicro_sumo.evaluation.idm_fit import calibrate_idm, idm_policy_accel
from macromicro_sumo.evaluation.krauss_fit import KraussParams
from macromicro_sumo.evaluation.micro_data import keyed_micro_pairs, micro_consistency
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.road.physics import leader_length_m

TAU_Q = np.interp(QUANTILE_LEVELS, [0.0, 0.05, 0.5, 0.75, 0.95, 1.0],
                  [0.6, 0.8, 1.1, 1.4, 1.8, 2.2])  # fmt: skip


def held_out_setup(ring_driver_follow):
    """The ring fixture's scenario, truth, prior, held-out runs, leader length, and two
    agents on its prior: ``policy`` with the drivers' tau quantiles, ``micro_only`` without."""
    sc, _, truth, prior, _, _ = ring_driver_follow
    held = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["held_out"]
    lead = leader_length_m(sc.policy.observation, typical_length(truth))
    make = lambda taus: Agent(observation=sc.policy.observation, prior="krauss",  # noqa: E731
                              prior_params=prior, residual_bound_mps2=0.0, driver_tau=taus)  # fmt: skip
    return sc, truth, prior, held, lead, {"policy": make(TAU_Q), "micro_only": make(None)}


def test_micro_consistency_scores_each_held_out_pair_with_its_drivers_tau(
    ring_driver_follow,
) -> None:
    sc, truth, prior, held, lead, agents = held_out_setup(ring_driver_follow)
    obs, acc, taus, _, record = held_out_pairs(sc, truth, held, agents, lead)
    want_obs, want_acc, keys = keyed_micro_pairs(sc, truth, held)
    np.testing.assert_array_equal(obs, want_obs)  # micro_pairs' held-out pairs
    np.testing.assert_array_equal(acc, want_acc)
    assert taus["micro_only"] is None  # no buffer: the prior's one tau, as before
    # The drivers' own taus: fitted on the held-out record with the agent's prior.
    p = {k: float(v) for k, v in prior.items() if k in KraussParams.__dataclass_fields__}
    params = KraussParams(**{k: float(np.float32(v)) for k, v in p.items()})
    drivers = observed_drivers(sc, truth, held)
    own = driver_taus(drivers.obs, drivers.accel, drivers.keys, params, lead,
                      sc.simulation.step_length_s)  # fmt: skip
    has_own = np.array([k in own for k in keys])
    assert has_own.sum() >= 50 and (~has_own).sum() >= 1, (has_own.sum(), len(keys))
    assert record["policy"]["pairs"] == len(keys)
    assert record["policy"]["own_tau"] == int(has_own.sum())
    got = taus["policy"]
    np.testing.assert_array_equal(
        got[has_own], [own[k] for k, m in zip(keys, has_own, strict=True) if m]
    )
    i = int(np.flatnonzero(~has_own)[0])  # the others: the deployment's draw for the driver
    assert (
        got[i]
        == DriverTaus(TAU_Q.astype(np.float32).astype(float), sc, keys[i][0])([keys[i][1]])[0]
    )
    assert (np.abs(got - prior["tau_s"]) > 0.05).mean() > 0.5  # not the prior's one tau
    # The score: the policy's NLL and RMSE with each pair's tau column, not the one tau.
    idm, _ = calibrate_idm(obs, acc, lead)
    micro = micro_consistency(agents, {"idm_calibrated": idm}, obs, acc, sc, lead, taus)
    one = micro_consistency(agents, {"idm_calibrated": idm}, obs, acc, sc, lead)
    a_min, a_max = sc.bounds.accel_mps2
    u = torch.as_tensor(np.clip(acc, a_min, a_max), dtype=torch.float32)
    with torch.no_grad():
        d = agents["policy"].dist(torch.as_tensor(with_tau(obs, got), dtype=torch.float32))
        nll = float(-d.log_prob(u).mean())
    row = micro.set_index("method")
    assert row.loc["policy", "nll"] == nll
    assert abs(row.loc["policy", "nll"] - one.set_index("method").loc["policy", "nll"]) > 1e-3
    # The methods without taus score as before.
    cols = list(one.columns.drop("method"))
    for m in ("micro_only", "idm_calibrated"):
        assert row.loc[m, cols].equals(one.set_index("method").loc[m, cols])
    assert row.loc["policy", "driver_tau"] == "in_sample"
    assert row.loc["micro_only", "driver_tau"] == "one"
    assert "driver_tau" not in one.columns  # no policy carries taus: the columns as before


def test_micro_consistency_out_of_sample_row_fits_on_first_half_scores_second(
    ring_driver_follow,
) -> None:
    """The in-sample row fits each held-out driver's tau on the pairs it scores; the
    out-of-sample row scores each driver's second half of pairs with the tau fitted on its
    first half (else the deployment's draw), on the ring's real short record."""
    sc, truth, prior, held, lead, agents = held_out_setup(ring_driver_follow)
    obs, acc, taus, later, record = held_out_pairs(sc, truth, held, agents, lead)
    _, _, keys = keyed_micro_pairs(sc, truth, held)
    assert later is not None and set(later.taus) == {"policy"}  # no buffer: no row
    m = later.later
    # Each driver's pairs split in their recorded order: first n // 2, then the rest.
    for k in set(keys):
        idx = np.array([i for i, kk in enumerate(keys) if kk == k])
        n = len(idx)
        assert m[idx].sum() == n - n // 2
        assert not m[idx[: n // 2]].any() and m[idx[n // 2 :]].all()
    assert 0.4 < m.mean() < 0.6, m.mean()
    # The taus: fitted on the first halves alone, with the agent's prior.
    p = {k: float(v) for k, v in prior.items() if k in KraussParams.__dataclass_fields__}
    params = KraussParams(**{k: float(np.float32(v)) for k, v in p.items()})
    first = [k for k, f in zip(keys, ~m, strict=True) if f]
    own = driver_taus(obs[~m], acc[~m], first, params, lead, sc.simulation.step_length_s)
    later_keys = [k for k, f in zip(keys, m, strict=True) if f]
    got = later.taus["policy"]
    has = later.own["policy"]
    assert len(got) == m.sum() and has.sum() >= 20, (has.sum(), len(got))
    np.testing.assert_array_equal(has, [k in own for k in later_keys])
    np.testing.assert_array_equal(
        got[has], [own[k] for k, h in zip(later_keys, has, strict=True) if h]
    )
    assert record["policy"]["out_of_sample"] == {"pairs": int(m.sum()), "own_tau": int(has.sum())}
    # The others: the deployment's draw for their driver.
    i = int(np.flatnonzero(~has)[0])
    draw = DriverTaus(TAU_Q.astype(np.float32).astype(float), sc, later_keys[i][0])
    assert got[i] == draw([later_keys[i][1]])[0]
    # The row: the second halves scored with these taus, beside the in-sample row.
    idm, _ = calibrate_idm(obs, acc, lead)
    micro = micro_consistency(agents, {"idm_calibrated": idm}, obs, acc, sc, lead, taus, later)
    row = micro.set_index("method")
    assert list(row.index) == [
        "policy",
        "policy_tau_out_of_sample",
        "micro_only",
        "idm_calibrated",
        "idm_calibrated_second_half",
    ]
    oos = row.loc["policy_tau_out_of_sample"]
    assert oos["driver_tau"] == "out_of_sample" and oos["n_pairs"] == m.sum()
    a_min, a_max = sc.bounds.accel_mps2
    u = torch.as_tensor(np.clip(acc[m], a_min, a_max), dtype=torch.float32)
    with torch.no_grad():
        d = agents["policy"].dist(torch.as_tensor(with_tau(obs[m], got), dtype=torch.float32))
    assert oos["nll"] == float(-d.log_prob(u).mean())
    assert row.loc["policy", "driver_tau"] == "in_sample" and row.loc["policy", "n_pairs"] == len(
        acc
    )
    # The IDM on the same second halves beside its row on every pair, so that they compare.
    pred = np.clip(idm_policy_accel(obs, idm, lead), a_min, a_max)
    half = row.loc["idm_calibrated_second_half"]
    assert half["n_pairs"] == m.sum() and half["driver_tau"] == ""
    u_m = np.clip(acc[m], a_min, a_max)
    assert half["action_rmse_mps2"] == float(np.sqrt(np.mean((pred[m] - u_m) ** 2)))
    assert row.loc["idm_calibrated", "n_pairs"] == len(acc)
    assert half["action_rmse_mps2"] != row.loc["idm_calibrated", "action_rmse_mps2"]

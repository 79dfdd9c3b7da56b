"""``policy.driver_follow = "by_vtype"``: the agent's ``driver_tau`` buffer is a table
(``env.driver_tau.vtype_table``: the pooled quantiles, then each vType's own, keyed by
``vtype_key``); a driver draws, at its hashed level, from its own vType's row where the
table has one (its vType read from the running SUMO), else from the pooled row; the
snapshot slots draw from the pooled row (``policy.driver_follow.follow_inputs``); a 1-D
buffer ("drawn") draws as before. The fit keeps a vType's quantiles where at least
``MIN_VTYPE_TAUS`` of its drivers give a tau. Real SUMO (game/cross, a red light)."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import torch
from red_light import CROSS, EDGES, red_light_queue

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS
from macromicro_sumo.env.driver_tau import (
    HANDOVER_RATE_S_PER_S,
    POOLED_KEY,
    DriverTaus,
    driver_tau_levels,
    pooled_quantiles,
    taus_at,
    vtype_key,
    vtype_table,
)
from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.evaluation.driver_follow import (
    MIN_STEADY_PAIRS,
    MIN_VTYPE_TAUS,
    driver_gap_taus,
    vtype_levels,
)
from macromicro_sumo.evaluation.krauss_fit import KraussParams
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.driver_follow import driver_tau_quantiles, follow_inputs
from macromicro_sumo.road.section import read_section
from macromicro_sumo.truth.section import record_run

POOLED = np.interp(QUANTILE_LEVELS, [0.0, 1.0], [1.0, 1.3])
# SUMO's default vType (the red light's cars) follows at twice the pooled taus.
DEFAULT = "DEFAULT_VEHTYPE"
OWN = 2.0 * POOLED


class Sc:
    seed = 7

    class simulation:
        step_length_s = 0.5


def test_a_driver_draws_from_its_vtypes_row_at_its_own_level() -> None:
    table = vtype_table(POOLED, {"car_idm": OWN, "truck": OWN + 1.0})
    assert table.shape == (3, len(QUANTILE_LEVELS) + 1)
    assert table[0, 0] == POOLED_KEY and table[1, 0] == vtype_key("car_idm")
    np.testing.assert_array_equal(pooled_quantiles(table), POOLED)
    np.testing.assert_array_equal(pooled_quantiles(POOLED), POOLED)
    # float32 holds the keys exactly (the agent's buffer).
    assert (table[:, 0].astype(np.float32).astype(float) == table[:, 0]).all()
    vids = ["a", "b", "c", "d"]
    types = {"a": "car_idm", "b": "truck", "c": "car", "d": "car_idm"}
    got = DriverTaus(table, Sc, 3, vtypes_of=lambda ids: [types[i] for i in ids])(vids)
    levels = driver_tau_levels(Sc.seed, 3, vids)
    rows = {"car_idm": OWN, "truck": OWN + 1.0, "car": POOLED}
    want = [
        np.interp(x, QUANTILE_LEVELS, rows[types[v]]) for x, v in zip(levels, vids, strict=True)
    ]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    # A 1-D buffer ("drawn"): the pooled draws, whatever the vTypes.
    plain = DriverTaus(POOLED, Sc, 3, vtypes_of=lambda ids: 1 / 0)(vids)
    np.testing.assert_array_equal(plain, taus_at(POOLED, levels))
    assert got[0] > plain[0] and got[2] == plain[2]


def test_two_vtypes_with_one_key_are_refused(monkeypatch) -> None:
    import macromicro_sumo.env.driver_tau as dt

    monkeypatch.setattr(dt, "vtype_key", lambda name: 5.0)
    with pytest.raises(ValueError, match="share a tau table key"):
        dt.vtype_table(POOLED, {"x": OWN, "y": OWN})


def test_the_fit_keeps_the_vtypes_with_enough_drivers() -> None:
    rng = np.random.default_rng(0)
    own, vtypes = {}, {}
    for i in range(40):
        own[(0, f"k{i}")], vtypes[(0, f"k{i}")] = float(rng.uniform(0.9, 1.2)), "car"
    for i in range(MIN_VTYPE_TAUS):
        own[(1, f"i{i}")], vtypes[(1, f"i{i}")] = float(rng.uniform(1.3, 2.0)), "car_idm"
    for i in range(MIN_VTYPE_TAUS - 1):
        own[(1, f"t{i}")], vtypes[(1, f"t{i}")] = 3.0, "truck"
    got = vtype_levels(own, vtypes)
    assert sorted(got) == ["car", "car_idm"]  # the trucks are one driver short
    idm = [t for k, t in own.items() if vtypes[k] == "car_idm"]
    assert got["car_idm"]["drivers"] == MIN_VTYPE_TAUS
    np.testing.assert_allclose(got["car_idm"]["levels_s"], np.quantile(idm, QUANTILE_LEVELS))
    assert got["car_idm"]["median_s"] > got["car"]["median_s"]


def test_the_policy_gets_a_table_only_with_by_vtype() -> None:
    record = {
        "drivers": 50,
        "levels_s": POOLED.tolist(),
        "by_vtype": {"car_idm": {"drivers": 12, "median_s": 2.3, "levels_s": OWN.tolist()}},
    }

    class Pol:
        driver_follow = "by_vtype"

    class Scn:
        policy = Pol

    q, n = driver_tau_quantiles(Scn, record)
    assert n == 50 and q.shape == (2, len(QUANTILE_LEVELS) + 1) and q[1, 0] == vtype_key("car_idm")
    # by_vtype_gap: the rows of the kept taus
    record["by_vtype_gap"] = {"truck": {"drivers": 10, "median_s": 3.0, "levels_s": OWN.tolist()}}
    Pol.driver_follow = "by_vtype_gap"
    qg, _ = driver_tau_quantiles(Scn, record)
    assert qg.shape == q.shape and qg[1, 0] == vtype_key("truck")
    Pol.driver_follow = "drawn"
    q1, _ = driver_tau_quantiles(Scn, record)
    np.testing.assert_array_equal(q1, POOLED)
    # The snapshot slots draw from the pooled row: as "drawn"'s.
    bank = SectionBank(**{f.name: np.ones((3, 5)) for f in fields(SectionBank) if f.init})
    a, _ = follow_inputs(bank, None, None, q, 11)
    b, _ = follow_inputs(bank, None, None, q1, 11)
    np.testing.assert_array_equal(a.driver_tau, b.driver_tau)


class Recorder(SectionSpeedDriver):
    """The deployment's driver, keeping every observation it made."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.rows: list[tuple[list[str], np.ndarray, int]] = []

    def observe(self, sim, vids, rows, st, *args, **kwargs):
        out = super().observe(sim, vids, rows, st, *args, **kwargs)
        self.rows.append((list(vids), out[0].copy(), self.steps))
        return out


def test_deployed_drivers_draw_from_their_sumo_vtypes_row(tmp_path: Path, cross_krauss) -> None:
    """In the deployment each driver's tau column rises (hand-over) to its draw on its
    vType's row: SUMO's default vType's, twice the pooled draws."""
    torch.manual_seed(5)
    table = vtype_table(POOLED, {DEFAULT: OWN, "truck": OWN + 1.0})
    a = Agent(16, observation="lookahead", prior="krauss", prior_params=cross_krauss,
              residual_bound_mps2=1.0, driver_tau=table)  # fmt: skip
    sc, sim = red_light_queue(tmp_path, 4, 40.0)
    drv = Recorder(sc, read_section(CROSS, EDGES, False), 0, policy_batch(a), "sumo")
    try:
        record_run(sim, sc, drv.section, 0, drv)
    finally:
        sim.close()
    seen: dict[str, list[tuple[int, float]]] = {}
    for vids, obs, step in drv.rows:
        for v, o in zip(vids, obs, strict=True):
            seen.setdefault(v, []).append((step, o[-1]))
    assert len(seen) == 4
    row = OWN.astype(np.float32).astype(float)  # the agent's buffer is float32
    drawn = dict(zip(seen, taus_at(row, driver_tau_levels(sc.seed, 0, list(seen))), strict=True))
    pooled = taus_at(POOLED, driver_tau_levels(sc.seed, 0, list(seen)))
    assert min(drawn.values()) > pooled.max()  # each on its vType's row, not the pooled one
    for v, rows in seen.items():
        step0, tau0 = rows[0]
        for step, tau in rows:
            want = min(drawn[v], tau0 + HANDOVER_RATE_S_PER_S * 0.5 * (step - step0))
            assert tau == pytest.approx(want, abs=1e-12)


def test_the_kept_tau_is_the_gap_a_driver_follows_at_pace() -> None:
    """``driver_gap_taus``: each driver's median supported tau over its steady following
    pairs; its braking pairs and fast-closing ones do not count, nor a driver with fewer
    than ``MIN_STEADY_PAIRS`` steady ones."""
    params = KraussParams(accel_mps2=2.6, decel_mps2=4.5, tau_s=1.0, min_gap_m=2.5,
                          speed_factor=1.0, relax_s=10.0)  # fmt: skip
    rng = np.random.default_rng(2)
    rows, acc, keys = [], [], []
    for name, tau, n in (
        ("krauss", 1.0, 30),
        ("idm", 1.6, 30),
        ("short", 1.3, MIN_STEADY_PAIRS - 1),
    ):
        v = rng.uniform(10.0, 22.0, n)
        gap = v * tau  # at pace: gap = v tau (the Krauss form's equilibrium)
        rows.append(np.column_stack([v, np.full(n, 30.0), gap + 5.0 + 2.5, np.zeros(n)]))
        acc.append(rng.uniform(-0.2, 0.2, n))
        keys += [(0, name)] * n
    # braking and closing pairs of the Krauss driver at a short gap: not steady
    v = np.full(20, 15.0)
    rows.append(np.column_stack([v, np.full(20, 30.0), 0.5 * v + 7.5, np.full(20, 3.0)]))
    acc.append(np.full(20, -2.0))
    keys += [(0, "krauss")] * 20
    got = driver_gap_taus(np.concatenate(rows), np.concatenate(acc), keys, params, 5.0)
    assert sorted(got) == [(0, "idm"), (0, "krauss")]
    assert got[(0, "krauss")] == pytest.approx(1.0, abs=1e-9)
    assert got[(0, "idm")] == pytest.approx(1.6, abs=1e-9)

"""``policy.driver_follow`` in Stage II (real SUMO: ring_two_lane, two runs of 40 s after a
30 s warm-up; real torch): a driver's tau is the same in the demand env and in the
deployment (a hash of seed, run and vehicle); the snapshot episodes' rollouts carry each
slot's tau as the last observation column and the prior brakes with it; PPO keeps the
quantiles in the agent, which a deployment then draws from."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from test_warmup_anchors import true_completion  # noqa: E402

from macromicro_sumo.data.section import section_snapshots  # noqa: E402
from macromicro_sumo.deploy.policy_batch import policy_batch  # noqa: E402
from macromicro_sumo.deploy.run import Drive, load_context, run_method  # noqa: E402
from macromicro_sumo.env.demand import DemandCore  # noqa: E402
from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS  # noqa: E402
from macromicro_sumo.env.driver_tau import DriverTaus  # noqa: E402
from macromicro_sumo.env.section import SectionCore  # noqa: E402
from macromicro_sumo.env.section_bank import build_section_bank  # noqa: E402
from macromicro_sumo.evaluation.driver_follow import following, pair_taus  # noqa: E402
from macromicro_sumo.evaluation.micro_data import keyed_micro_pairs  # noqa: E402
from macromicro_sumo.policy.agent import Agent  # noqa: E402
from macromicro_sumo.policy.chosen_prior import (  # noqa: E402
    CHOICE_FILE,
    apply_choice,
    read_choice,
    write_choice,
)
from macromicro_sumo.policy.demand_rollout import set_driver_draws  # noqa: E402
from macromicro_sumo.policy.driver_follow import follow_choice, follow_inputs  # noqa: E402
from macromicro_sumo.policy.ppo import train_policy  # noqa: E402
from macromicro_sumo.policy.rollout import collect  # noqa: E402
from macromicro_sumo.sumo.inputs import scenario_inputs  # noqa: E402

TAU_Q = np.interp(QUANTILE_LEVELS, [0.0, 0.05, 0.5, 0.75, 0.95, 1.0],
                  [1.0, 1.035, 1.075, 1.37, 1.79, 2.0])  # fmt: skip


@pytest.fixture(scope="module")
def ring(ring_driver_follow):
    """tests/conftest.py's ring: (sc, gt, truth, prior, pairs, the fit's record)."""
    return ring_driver_follow


def prior_agent(sc, prior) -> Agent:
    return Agent(observation=sc.policy.observation, prior="krauss", prior_params=prior,
                 residual_bound_mps2=0.0, driver_tau=TAU_Q)  # fmt: skip


def test_a_driver_has_one_tau_in_the_demand_env_and_the_deployment(ring, tmp_path) -> None:
    sc, gt, truth, prior, _, _ = ring
    agent = prior_agent(sc, prior)
    core = DemandCore(sc, truth, truth.runs, 10)
    demand: dict[str, float] = {}
    columns: dict[str, list[float]] = {}
    try:
        set_driver_draws(core, agent)  # as collect_demand sets them
        core.reset(0, 10.0)
        for _ in range(6):
            vids, obs = core.observe()
            assert obs.shape[1] == core.obs_dim == 7  # lookahead + the tau
            drawn = core.taus(vids)  # the draws themselves, without the hand-over
            for v, t, col in zip(vids, drawn, obs[:, -1], strict=True):
                assert demand.setdefault(v, t) == t
                columns.setdefault(v, []).append(float(col))
            core.step(np.zeros(len(vids)))
    finally:
        core.close()
    # Handed over as in the deployment (the agent's Krauss prior): from the tau the first
    # gap supports, at least the lowest quantile, rising to the draw, never above it.
    for v, col in columns.items():
        assert np.all(np.diff(col) >= -1e-6) and max(col) <= demand[v] + 1e-6
        assert min(col) >= np.float32(TAU_Q[0]) - 1e-6
    assert any(col[0] < demand[v] - 0.05 for v, col in columns.items())  # some handed over
    act = policy_batch(agent)
    seen: dict[str, float] = {}
    make = act.driver_taus

    def recording(sc_, run):
        taus = make(sc_, run)

        def call(vids, obs=None, step=None):
            drawn = taus(vids)  # the draws themselves, without the hand-over
            for v, t in zip(vids, drawn, strict=True):
                assert seen.setdefault(v, t) == t
            got = taus(vids, obs, step)  # handed over (env.driver_tau): at most the draw
            assert (got <= drawn).all()
            return got

        return call

    act.driver_taus = recording
    run_method(load_context(sc, gt), Drive(act=act), tmp_path, [0])
    common = sorted(set(demand) & set(seen))
    assert len(common) >= 10
    assert [demand[v] for v in common] == [seen[v] for v in common]
    assert len({round(t, 6) for t in seen.values()}) > len(seen) // 2  # drawn, not one


def test_snapshot_rollouts_carry_each_slots_tau_and_ppo_keeps_the_quantiles(ring, tmp_path) -> None:
    sc, _, truth, prior, (obs, acc, _), _ = ring
    torch.set_num_threads(1)
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_completion, 10, 0)
    net = scenario_inputs(sc).net_file
    taus_bank, pairs = follow_inputs(bank, (obs, acc), prior, TAU_Q, sc.seed)
    assert bank.driver_tau is None and taus_bank.driver_tau.shape == bank.valid.shape
    assert pairs[0].shape[1] == obs.shape[1] + 1
    assert (pairs[0][:, -1] == prior["tau_s"]).all()
    again, _ = follow_inputs(bank, None, prior, TAU_Q, sc.seed)
    np.testing.assert_array_equal(again.driver_tau, taus_bank.driver_tau)  # seeded
    core = SectionCore(sc, truth.section, taus_bank, net, seed=0)
    agent = prior_agent(sc, prior)
    eps = np.arange(min(3, len(bank)))
    try:
        ro = collect(agent, core, eps, 0.0, 4, torch.Generator().manual_seed(0))
    finally:
        core.close()
    assert ro.obs.shape[-1] == 7
    want = np.broadcast_to(taus_bank.driver_tau[eps][:, None, :], ro.obs.shape[:-1])
    np.testing.assert_array_equal(ro.obs[..., -1], want.astype(np.float32))
    one = Agent(observation=sc.policy.observation, prior="krauss", prior_params=prior,
                residual_bound_mps2=0.0)  # fmt: skip
    o = torch.as_tensor(ro.obs[ro.active])
    with torch.no_grad():
        own, single = agent.mean_action(o), one.mean_action(o[:, :6])
    assert not torch.equal(own, single)  # the rows' own taus moved the prior

    def make_core(b, seed):
        return SectionCore(sc, truth.section, b, net, seed=seed)

    res = train_policy(sc, bank, tmp_path, updates=1, progress=False, make_core=make_core,
                       prior_params=prior, recorded_pairs=(obs, acc),
                       driver_tau=TAU_Q)  # fmt: skip
    np.testing.assert_array_equal(res["agent"].driver_tau.numpy(), TAU_Q.astype(np.float32))
    ck = torch.load(tmp_path / "policy.pt", weights_only=True)
    assert ck["driver_follow"] == "drawn" and "driver_tau" in ck["state_dict"]


def test_the_fit_records_the_quantiles_drawn_from(ring) -> None:
    """The Krauss fit's record keeps every quantile of the drivers' taus (or None under 30
    drivers); "drawn" takes them, "none" nothing, and a record without them keeps the one
    tau."""
    sc, _, truth, prior, _, fitted = ring
    record = fitted["driver_taus"]
    assert "levels_s" in record
    off = replace(sc, policy=replace(sc.policy, driver_follow="none"))
    assert follow_choice(off, fitted, prior, None) == (None, None)
    q, got = follow_choice(sc, fitted, prior, None)
    assert got["setting"] == "drawn" and got["drivers_with_tau"] == record["drivers"]
    assert (q is None) == (record["drivers"] < 30) == (record["levels_s"] is None)
    assert got["chosen"] == ("none" if q is None else "drawn")
    made = {**fitted, "driver_taus": {**record, "levels_s": TAU_Q.tolist(), "drivers": 40}}
    q, got = follow_choice(sc, made, prior, None)
    np.testing.assert_array_equal(q, TAU_Q)
    assert got["chosen"] == "drawn" and got["drivers_with_tau"] == 40


def test_each_likelihood_pair_takes_its_own_drivers_tau(ring) -> None:
    """Two observed drivers on the ring's recorded scenes who follow at different taus
    (1.2 s and 2.0 s, their actions the prior's at that tau): each pair carries its own
    driver's tau (``pair_taus``; a driver without a fitted one the deployment's draw for
    it) into the likelihood pairs (``follow_inputs``), where the prior with each driver's
    own tau gives that driver's actions a higher likelihood than with the other's tau or
    the prior's one. Before, every pair carried the prior's one tau."""
    sc, _, truth, prior, pairs, fitted = ring
    obs, acc, keys = keyed_micro_pairs(sc, truth, truth.runs)
    np.testing.assert_array_equal(obs, pairs[0])  # micro_pairs' pairs, now with drivers
    assert (pairs[2] is None) == (fitted["driver_taus"]["levels_s"] is None)
    near = following(obs)
    counts: dict = {}
    for k in np.asarray(keys, dtype=object)[near]:
        counts[tuple(k)] = counts.get(tuple(k), 0) + 1
    a, b = sorted(counts, key=lambda k: (-counts[k], k))[:2]
    own = {a: 1.2, b: 2.0}
    taus = pair_taus(sc, keys, own, TAU_Q)
    assert pair_taus(sc, keys, own, None) is None  # under 30 drivers: the prior's one tau
    is_a = np.array([k == a for k in keys])
    is_b = np.array([k == b for k in keys])
    assert (taus[is_a] == 1.2).all() and (taus[is_b] == 2.0).all()
    other = ~(is_a | is_b)  # the deployment's draw for each of the other drivers
    run, vid = keys[int(np.flatnonzero(other)[0])]
    drawn = DriverTaus(TAU_Q.astype(np.float32).astype(float), sc, run)([vid])[0]
    assert taus[int(np.flatnonzero(other)[0])] == drawn
    agent = prior_agent(sc, prior)
    f32 = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
    one = agent.prior_accel(f32(np.c_[obs, np.full(len(obs), 1.2)])).numpy()
    two = agent.prior_accel(f32(np.c_[obs, np.full(len(obs), 2.0)])).numpy()
    assert np.abs(one - two)[near & (is_a | is_b)].max() > 0.5  # the taus part them
    acc = np.where(is_a, one, np.where(is_b, two, acc))  # their own headways
    bank = build_section_bank(sc, truth, section_snapshots(truth, sc, truth.runs),
                              true_completion, 4, 0)  # fmt: skip
    _, got = follow_inputs(bank, (obs, acc, taus), prior, TAU_Q, sc.seed)
    np.testing.assert_array_equal(got[0][:, -1], taus.astype(obs.dtype))

    def logp(rows: np.ndarray, column: np.ndarray | float) -> float:
        o = f32(np.c_[obs[rows], np.broadcast_to(column, rows.sum())])
        with torch.no_grad():
            return float(agent.dist(o).log_prob(f32(acc[rows])).mean())

    for rows, mine, theirs in ((is_a & near, 1.2, 2.0), (is_b & near, 2.0, 1.2)):
        carried = logp(rows, got[0][rows, -1])
        assert carried == logp(rows, mine)
        assert carried > logp(rows, theirs) + 0.1
        assert carried > logp(rows, prior["tau_s"]) + 0.1


def test_the_prior_choice_keeps_each_pairs_tau(ring, tmp_path) -> None:
    """The choice's pairs file keeps each pair's driver's tau and gives it back; one made
    without them is made again where ``policy.driver_follow`` draws taus, and read as it
    is with "none"."""
    sc, gt, _, prior, (obs, acc, _), fitted = ring
    assert sc.policy.prior == "krauss"
    made = {**fitted, "driver_taus": {**fitted["driver_taus"], "levels_s": TAU_Q.tolist()}}
    taus = np.linspace(1.0, 2.0, len(acc))
    path = tmp_path / CHOICE_FILE
    write_choice(path, sc, gt, (sc, (prior, {"prior": made}, (obs, acc, taus))), 0.0)
    record = read_choice(path, sc, gt)
    assert record is not None
    got = apply_choice(record, sc, path)[1][2]
    np.testing.assert_array_equal(got[0], obs)
    np.testing.assert_array_equal(got[2], taus)
    write_choice(path, sc, gt, (sc, (prior, {"prior": made}, (obs, acc, None))), 0.0)
    assert read_choice(path, sc, gt) is None
    off = replace(sc, policy=replace(sc.policy, driver_follow="none"))
    record = read_choice(path, off, gt)
    assert record is not None and apply_choice(record, off, path)[1][2][2] is None

"""PPO with demand episodes (``policy.demand_rollout``): per-vehicle GAE with truncation
and collision terminals, and a short training run that mixes both kinds of episodes."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import merge_scenario  # noqa: E402

from macromicro_sumo.data.section import section_snapshots  # noqa: E402
from macromicro_sumo.env.demand import DemandCore  # noqa: E402
from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS, driver_levels, factors_at  # noqa: E402
from macromicro_sumo.env.section import SectionCore  # noqa: E402
from macromicro_sumo.env.section_bank import build_section_bank  # noqa: E402
from macromicro_sumo.policy.agent import Agent  # noqa: E402
from macromicro_sumo.policy.demand_rollout import collect_demand, vehicle_gae  # noqa: E402
from macromicro_sumo.policy.ppo import train_policy  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402


def test_vehicle_gae_bootstraps_a_truncation_and_not_a_collision() -> None:
    r = np.array([1.0, 1.0], dtype=np.float32)
    v = np.array([0.5, 2.0], dtype=np.float32)
    g, lam = 0.9, 0.5
    adv, ret = vehicle_gae(r, v, terminal=False, gamma=g, lam=lam)
    d1 = 1.0 + g * 2.0 - 2.0  # bootstrapped with the last value
    d0 = 1.0 + g * 2.0 - 0.5
    np.testing.assert_allclose(adv, [d0 + g * lam * d1, d1], rtol=1e-6)
    np.testing.assert_allclose(ret, adv + v)
    adv_t, _ = vehicle_gae(r, v, terminal=True, gamma=g, lam=lam)
    np.testing.assert_allclose(adv_t[1], 1.0 - 2.0)  # nothing after a collision


def true_completion(s):
    """The true hidden vehicles as the 'generated' ones, observed vehicles first."""
    order = np.argsort(np.where(s.valid, np.where(s.observed, 0, 1), 2), axis=1, kind="stable")
    take = lambda a: np.take_along_axis(a, order, 1)  # noqa: E731
    return take(s.lane), take(s.arc_m), take(s.speed_mps), take(s.valid), take(s.hidden)


@pytest.fixture(scope="module")
def merge(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("demand_train")
    path = merge_scenario(
        folder,
        {"warmup_s": 60.0, "duration_s": 60.0, "n_runs": 2},
        policy={
            "observation": "lookahead",
            "episodes": "mixed",
            "demand_horizon_s": 10.0,
            "episodes_per_update": 2,
            "collision_penalty": 1.0,
        },
    )
    sc = load_scenario(path)
    gt = simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(gt, sc), Path(sc.network.net_file)


def test_mixed_training_learns_from_demand_episodes(merge, tmp_path: Path) -> None:
    sc, truth, net = merge
    torch.set_num_threads(1)
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_completion, 10, 0)

    def make_core(b, seed):
        return SectionCore(sc, truth.section, b, net, seed=seed)

    def make_demand():
        return DemandCore(sc, truth, truth.runs, 20)

    res = train_policy(
        sc, bank, tmp_path, updates=2, progress=False, make_core=make_core, make_demand=make_demand
    )
    row = res["log"][-1]
    assert row["demand_vehicle_steps"] > 20 * 5 and 0.0 < row["demand_r_macro"] <= 1.0
    assert np.isfinite(row["r_macro"])
    # Behaviour cloning has no policy gradient: no demand episodes.
    res = train_policy(
        sc,
        bank,
        tmp_path / "bc",
        updates=1,
        progress=False,
        objective="micro_only",
        make_core=make_core,
        make_demand=make_demand,
    )
    assert "demand_r_macro" not in res["log"][-1]
    # Snapshot episodes only: the same as without a demand source.
    snap = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, episodes="snapshots"))
    a = train_policy(snap, bank, tmp_path / "a", updates=1, progress=False, make_core=make_core)
    b = train_policy(
        snap,
        bank,
        tmp_path / "b",
        updates=1,
        progress=False,
        make_core=make_core,
        make_demand=make_demand,
    )
    for (k, x), y in zip(
        a["agent"].state_dict().items(), b["agent"].state_dict().values(), strict=True
    ):
        assert torch.equal(x, y), k


def test_demand_rollouts_give_drivers_the_agents_desired_speed_factors(merge) -> None:
    """``policy.driver_speed = "drawn"``: ``collect_demand`` drives each vehicle with the
    factor the deployment draws from the agent's quantiles for (seed, run, vehicle); the
    limits it observed are the section's times that factor. An agent without quantiles:
    every driver the limits as they are."""
    sc0, truth, _ = merge
    sc = dataclasses.replace(sc0, policy=dataclasses.replace(sc0.policy, driver_speed="drawn"))
    q = np.linspace(0.8, 1.25, len(QUANTILE_LEVELS))
    gen = torch.Generator().manual_seed(0)
    run = int(truth.runs[0])
    limits = set(np.round(truth.section.limits_mps.ravel(), 9).tolist())
    core = DemandCore(sc, truth, truth.runs, 20)
    try:
        for quantiles in (q, None):
            agent = Agent(observation="lookahead", driver_speed=quantiles)
            db = collect_demand(agent, core, [(run, 70.0)], 1.0, 0.0, 0.99, 0.95, gen)
            seen = set(np.round(db.obs[:, 1], 4).tolist())
            if quantiles is None:
                assert core.drivers is None and seen <= {round(x, 4) for x in limits}
                continue
            ids = sorted(core.drivers.factor)
            assert len(ids) >= 5 and db.vehicle_steps > 20 * 5
            want = factors_at(agent.driver_speed.double().numpy(), driver_levels(sc.seed, run, ids))
            np.testing.assert_allclose([core.drivers.factor[v] for v in ids], want, rtol=1e-12)
            assert len(seen) >= len(ids) and np.ptp(want) > 0.1  # each its own limits
    finally:
        core.close()

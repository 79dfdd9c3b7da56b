"""Stage II: the SUMO env core and PPO, on a small real ground truth and generator."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch
from policy_rings import ring_core, ring_scenario, true_state_bank

from macromicro_sumo import cli
from macromicro_sumo.policy.ppo import clipped_actions, gae


def test_gae_matches_hand_computation():
    r = np.array([1.0, 0.0, 2.0])
    v = np.array([0.5, 0.2, 1.0])
    adv, ret = gae(r, v, gamma=0.9, lam=0.8)
    d2 = 2.0 - 1.0
    d1 = 0.0 + 0.9 * 1.0 - 0.2
    d0 = 1.0 + 0.9 * 0.2 - 0.5
    a2 = d2
    a1 = d1 + 0.9 * 0.8 * a2
    a0 = d0 + 0.9 * 0.8 * a1
    np.testing.assert_allclose(adv, [a0, a1, a2])
    np.testing.assert_allclose(ret, adv + v)


def test_clipped_actions_counts_share():
    out, share = clipped_actions(np.array([-2.0, 0.0, 0.3, 0.9]), -1.1, 0.5)
    np.testing.assert_allclose(out, [-1.1, 0.0, 0.3, 0.5])
    assert share == 0.5


@pytest.fixture(scope="module")
def small_gt(small_ring_gt, tmp_path_factory):
    folder = tmp_path_factory.mktemp("policy")
    return ring_scenario(folder, {"policy.updates": 6, "generator.epochs": 5}), small_ring_gt


def _bank(sc, gt_dir, k):
    # Completing with the true hidden states isolates the env from the generator.
    return true_state_bank(sc, gt_dir, k, split="train")[0]


def test_replay_of_all_vehicles_reproduces_ground_truth(small_gt):
    """Observed vehicles replay recorded speeds; with the true actions for the hidden
    vehicle too, the env reproduces the recorded fleet exactly (speed mode 0)."""
    sc, gt_dir = small_gt
    bank = _bank(sc, gt_dir, 1)
    core = ring_core(sc, bank)
    try:
        for ep in range(3):
            core.reset(ep)
            h = bank.hidden[ep]
            for t in range(sc.policy.horizon):
                res = core.step(bank.gt_accel_mps2[ep, t][h])
                assert not res.error and not res.collision
                # The bank replays the observed vehicles (NaN for the hidden, whose recorded
                # actions drive them here).
                want = bank.replay_speed_mps[ep, t + 1]
                seen = np.isfinite(want)
                assert seen.sum() == bank.valid[ep].sum() - h.sum()
                np.testing.assert_allclose(core.speed[seen], want[seen], atol=1e-6)
                assert 0.0 < res.r_macro <= 1.0
    finally:
        core.close()


def test_actions_are_clipped_to_bounds(small_gt):
    sc, gt_dir = small_gt
    bank = _bank(sc, gt_dir, 2)
    core = ring_core(sc, bank)
    try:
        core.reset(0)
        h = bank.hidden[0]
        v0 = core.speed[h].copy()
        core.step(np.array([50.0, -50.0]))
        dv = (core.speed[h] - v0) / sc.simulation.step_length_s
        np.testing.assert_allclose(
            dv, [sc.bounds.accel_mps2[1], sc.bounds.accel_mps2[0]], atol=1e-6
        )
    finally:
        core.close()


def test_train_policy_cli_writes_policy_and_log(small_gt, tmp_path):
    sc, gt_dir = small_gt
    gen_dir = tmp_path / "gen"
    torch.manual_seed(0)
    assert (
        cli.main(
            ["train-generator", sc.source, "--data", str(gt_dir), "--out", str(gen_dir), "--quiet"]
        )
        == 0
    )
    pol = tmp_path / "pol"
    assert (
        cli.main(
            [
                "train-policy",
                sc.source,
                "--data",
                str(gt_dir),
                "--generator",
                str(gen_dir / "generator.pt"),
                "--out",
                str(pol),
                "--quiet",
            ]
        )
        == 0
    )
    log = pd.read_csv(pol / "policy_train_log.csv")
    assert {
        "r_macro",
        "r_micro_per_pair",
        "pg_loss",
        "v_loss",
        "entropy",
        "kl",
        "collisions",
    } <= set(log.columns)
    # The likelihood of the observed vehicles' actions improves with training.
    assert log["r_micro_per_pair"].iloc[-1] > log["r_micro_per_pair"].iloc[0]
    assert (pol / "policy.pt").is_file()

"""``deploy.action = "sample"``: every driven vehicle's acceleration drawn from the policy's
Gaussian each step, from a generator seeded by the scenario's seed and the run, before the
bounds and the safety layer. The draws have the policy's mean and std; in real SUMO on a
small merge a sampled deployment differs from the mean action's, repeats itself exactly
with the same seed, and collides nowhere; "mean" stays the default."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from deploy_nets import idm_agent, merge_scenario

from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.deploy.run import ACTION_STREAM, Drive, load_context, run_method, sampled
from macromicro_sumo.deploy.stage import method_drive
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section


def test_draws_have_the_policys_mean_and_std_and_repeat_with_the_seed() -> None:
    """Around a mean that varies by vehicle, the draws' residuals are N(0, std^2) (mean and
    std within 4 standard errors over 20,000 vehicle-steps), one per vehicle and call; the
    same seed gives the same draws, another run other ones; the driver's speed factors
    (``policy.driver_speed``) pass through."""
    std = 0.4

    def act(obs: np.ndarray) -> np.ndarray:
        return -0.1 * obs[:, 0]

    act.driver_speeds = "factors"  # what the driver reads off the action function
    obs = np.column_stack([np.linspace(0.0, 30.0, 200), np.full(200, 30.0)])

    def draws(run: int) -> np.ndarray:
        draw = sampled(act, std, np.random.default_rng([9, run, ACTION_STREAM]))
        assert draw.driver_speeds == "factors"
        return np.stack([draw(obs) for _ in range(100)])

    got = draws(0)
    assert got.shape == (100, 200)
    resid = got - act(obs)
    n = resid.size
    assert abs(resid.mean()) < 4 * std / math.sqrt(n), resid.mean()
    assert abs(resid.std() - std) < 4 * std / math.sqrt(2 * n), resid.std()
    # independent across vehicles and steps: no correlation between neighbours
    assert abs(np.corrcoef(resid[:, :-1].ravel(), resid[:, 1:].ravel())[0, 1]) < 0.03
    np.testing.assert_array_equal(draws(0), got)
    assert not np.any(draws(1) == got)


def test_the_option_sets_the_drive_of_learned_methods_only(tmp_path: Path) -> None:
    """ "mean" (the default) drives with the mean action, no std; "sample" with the policy's
    own learned std (exp log_std), recorded in the method's manifest; the IDM baselines
    and SUMO's defaults are vType switches either way."""
    path = merge_scenario(tmp_path, {"warmup_s": 10.0, "duration_s": 30.0, "n_runs": 2})
    sc = load_scenario(path)
    assert sc.deploy.action == "mean" and "action" not in sc.to_dict()["deploy"]
    agent = idm_agent(sc.policy.observation, 30.0, steps=10)
    with torch.no_grad():
        agent.log_std.fill_(math.log(0.25))
    drive, record = method_drive("policy", sc, {"policy": agent}, None)
    assert drive.sample_std_mps2 == 0.0 and record["action"] == "mean"
    sample = load_scenario(path, {"deploy.action": "sample"})
    assert sample.digest() != sc.digest()
    for name in ("policy", "policy_no_safety", "micro_only", "macro_only"):
        drive, record = method_drive(name, sample, {name: agent}, None)
        assert drive.sample_std_mps2 == pytest.approx(0.25, rel=1e-6), name
        assert record["action"] == "sample" and record["action_std_mps2"] == drive.sample_std_mps2
    drive, _ = method_drive("sumo_default", sample, {}, None)
    assert drive.act is None and drive.sample_std_mps2 == 0.0


@pytest.fixture(scope="module")
def merge_truth(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(scenario file, ground truth) of the on-ramp merge: 2 runs of 30 s warm-up + 90 s."""
    folder = tmp_path_factory.mktemp("sampled_merge")
    path = merge_scenario(
        folder,
        {"warmup_s": 30.0, "duration_s": 90.0, "n_runs": 2},
        policy={"observation": "lookahead"},
    )
    return path, simulate_section(load_scenario(path), folder / "gt", progress=False)


def _deploy(path: Path, gt: Path, action: str, out: Path) -> pd.DataFrame:
    """The IDM-cloned policy (std 0.5 m/s^2) deployed on the held-out run: trajectories."""
    sc = load_scenario(path, {"deploy.action": action})
    agent = idm_agent(sc.policy.observation, 30.0)
    with torch.no_grad():
        agent.log_std.fill_(math.log(0.5))
    drive, _ = method_drive("policy", sc, {"policy": agent}, None)
    res = run_method(load_context(sc, gt), drive, out)
    runs = res.runs.iloc[0]
    assert runs["collisions"] == 0 and runs["teleports"] == 0, (action, runs.to_dict())
    assert runs["vehicle_steps_driven"] > 2000, runs.to_dict()
    return res.trajectories


def test_sampled_deployment_differs_from_the_mean_repeats_and_does_not_collide(
    merge_truth: tuple[Path, Path], tmp_path: Path
) -> None:
    """Real SUMO, the merge with its on-ramp: the mean action's deployment is the one a
    plain ``Drive(act=policy_batch(..., deploy.actor_dtype))`` gives (the default unchanged,
    bit for bit); the sampled one differs from it, is the same again with the same seed,
    and jitters: the driven vehicles' step-to-step acceleration changes spread wider than
    the mean's."""
    path, gt = merge_truth
    mean = _deploy(path, gt, "mean", tmp_path / "mean")
    sc = load_scenario(path)
    act = policy_batch(idm_agent(sc.policy.observation, 30.0), sc.deploy.actor_dtype)
    plain = run_method(load_context(sc, gt), Drive(act=act), tmp_path / "plain")
    pd.testing.assert_frame_equal(plain.trajectories, mean, check_exact=True)
    first = _deploy(path, gt, "sample", tmp_path / "sample")
    again = _deploy(path, gt, "sample", tmp_path / "again")
    pd.testing.assert_frame_equal(first, again, check_exact=True)
    assert len(first) != len(mean) or not np.array_equal(first["speed_mps"], mean["speed_mps"])

    def jerk_std(traj: pd.DataFrame) -> float:
        driven = traj[~traj["observed"]].sort_values(["vehicle_id", "time_s"])
        return float(driven.groupby("vehicle_id")["accel_mps2"].diff().std())

    assert jerk_std(first) > 1.5 * jerk_std(mean), (jerk_std(first), jerk_std(mean))

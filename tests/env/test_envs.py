"""The public environments on the paper ring (a ring file: its closed one-lane section) pass
the official gymnasium and PettingZoo checkers."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SMALL_RING, write_scenario
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

from macromicro_sumo import cli
from macromicro_sumo.env.section_envs import SectionHiddenEnv, SectionHiddenParallelEnv
from macromicro_sumo.env.wrappers import ENV_ID
from macromicro_sumo.errors import UserError


@pytest.fixture(scope="module")
def gt(tmp_path_factory, small_ring_gt):
    """(scenario, ground truth, generator) of the small ring; a generator of 3 epochs."""
    folder = tmp_path_factory.mktemp("envs")
    path = write_scenario(folder, {**SMALL_RING, "generator.epochs": 3})
    gen = folder / "gen"
    args = ["train-generator", str(path), "--data", str(small_ring_gt), "--out", str(gen)]
    assert cli.main([*args, "--quiet"]) == 0
    return path, small_ring_gt, gen / "generator.pt"


def test_gymnasium_env_passes_check_env(gt):
    path, data, gen = gt
    env = SectionHiddenEnv(path, data, gen)
    try:
        check_env(env, skip_render_check=True)
    finally:
        env.close()


def test_gymnasium_env_is_registered(gt):
    import gymnasium

    path, data, gen = gt
    env = gymnasium.make(ENV_ID, scenario=path, data=data, generator=gen)
    try:
        obs, info = env.reset(seed=3)
        d = env.observation_space.shape[0]
        assert obs.shape == (d,) and info["observed_obs"].shape == (4, d)
        steps, done = 0, False
        while not done:
            obs, r, term, trunc, info = env.step(np.array([0.0], np.float32))
            assert 0.0 < r <= 1.0
            steps += 1
            done = term or trunc
        assert steps == 10  # H policy steps
    finally:
        env.close()


def test_pettingzoo_env_passes_parallel_api_test(gt):
    path, data, gen = gt
    env = SectionHiddenParallelEnv(path, data, gen)
    try:
        parallel_api_test(env, num_cycles=50)
    finally:
        env.close()


def reset_with_agents(env, at_least: int) -> tuple[list[str], dict]:
    """Reset ``env`` (seeds 0, 1, ...) until an episode has ``at_least`` hidden vehicles
    (each snapshot hides its own K, ``policy.hidden_train``): (its agents, their infos)."""
    for seed in range(200):
        _, infos = env.reset(seed=seed)
        if len(env.agents) >= at_least:
            return list(env.agents), infos
    raise AssertionError(f"no episode with {at_least} hidden vehicles in 200 resets")


def test_bad_actions_name_the_agent(gt):
    path, data, gen = gt
    env = SectionHiddenParallelEnv(path, data, gen)
    try:
        a, b = reset_with_agents(env, 2)[0][:2]
        with pytest.raises(ValueError, match=f"agent {b}: action must be finite"):
            env.step({x: np.array([0.0]) for x in env.agents} | {b: np.array([np.nan])})
        with pytest.raises(ValueError, match=f"agent {a}: action must have shape"):
            env.step({x: np.array([0.0]) for x in env.agents} | {a: np.zeros(3)})
    finally:
        env.close()


def test_second_env_in_one_process_is_refused_clearly(gt):
    path, data, gen = gt
    first = SectionHiddenEnv(path, data, gen)
    first.reset(seed=0)
    second = SectionHiddenEnv(path, data, gen)
    try:
        with pytest.raises(UserError, match="one per process"):
            first.step(np.array([0.0], np.float32))
        second.reset(seed=0)
        second.step(np.array([0.0], np.float32))
    finally:
        first.close()
        second.close()


def test_every_agent_gets_its_own_info_dict(gt):
    path, data, gen = gt
    env = SectionHiddenParallelEnv(path, data, gen)
    try:
        agents, infos = reset_with_agents(env, 3)
        assert len({id(i) for i in infos.values()}) == len(infos) >= 3
        _, _, _, _, infos = env.step({a: np.array([0.0]) for a in env.agents})
        infos[agents[0]]["terminal_observation"] = "only the first agent's"
        assert all("terminal_observation" not in infos[a] for a in agents[1:])
    finally:
        env.close()


def test_render_mode_none_is_accepted_and_possible_agents_fit_the_bank(gt):
    path, data, gen = gt
    env = SectionHiddenParallelEnv(path, data, gen, render_mode=None)
    try:
        most = int(env.core.bank.hidden.sum(axis=1).max())
        assert env.render_mode is None and len(env.possible_agents) == most
        for seed in range(4):
            env.reset(seed=seed)
            assert set(env.agents) <= set(env.possible_agents)
    finally:
        env.close()
    with pytest.raises(ValueError, match="render_mode 'human' is not supported"):
        SectionHiddenEnv(path, data, gen, render_mode="human")


def test_env_made_by_gymnasium_lives_on_after_check_env(gt):
    """check_env builds and closes a second env from the spec; the first one's reset starts
    its SUMO run again."""
    import gymnasium

    path, data, gen = gt
    env = gymnasium.make(ENV_ID, scenario=path, data=data, generator=gen)
    try:
        check_env(env, skip_render_check=True)  # the call: on gymnasium.make's env
        env.reset(seed=1)
        for _ in range(3):
            _, r, term, trunc, info = env.step(np.array([0.0], np.float32))
            assert not info["error"] and 0.0 < r <= 1.0
    finally:
        env.close()


def test_displaced_env_says_so_and_reloads_at_reset(gt):
    path, data, gen = gt
    first = SectionHiddenEnv(path, data, gen)
    second = SectionHiddenEnv(path, data, gen)
    try:
        second.reset(seed=0)
        first.reset(seed=0)  # takes SUMO back from the second
        first.step(np.array([0.0], np.float32))
        with pytest.raises(UserError, match="reset\\(\\) starts this one's again"):
            second.step(np.array([0.0], np.float32))
        for env in (second, first, second):
            env.reset(seed=2)
            _, _, _, _, info = env.step(np.array([0.0], np.float32))
            assert not info["error"]
    finally:
        first.close()
        second.close()


def test_in_process_vector_envs_are_refused_when_built(gt):
    import gymnasium
    from stable_baselines3.common.vec_env import DummyVecEnv

    path, data, gen = gt
    kwargs = dict(scenario=path, data=data, generator=gen)
    with pytest.raises(UserError, match="SyncVectorEnv would run 2 .*AsyncVectorEnv"):
        gymnasium.make_vec(ENV_ID, num_envs=2, vectorization_mode="sync", **kwargs)
    with pytest.raises(UserError, match="DummyVecEnv would run 3 .*SubprocVecEnv"):
        DummyVecEnv([lambda: gymnasium.make(ENV_ID, **kwargs)] * 3)
    one = gymnasium.make_vec(ENV_ID, num_envs=1, vectorization_mode="sync", **kwargs)
    try:
        one.reset(seed=0)
        one.step(np.zeros((1, 1), np.float32))
    finally:
        one.close()


def test_async_vector_env_steps(gt):
    import gymnasium

    path, data, gen = gt
    vec = gymnasium.make_vec(
        ENV_ID,
        num_envs=2,
        vectorization_mode="async",
        scenario=path,
        data=data,
        generator=gen,
    )
    try:
        obs, _ = vec.reset(seed=0)
        assert obs.shape[0] == 2
        for _ in range(12):  # past one horizon: autoreset too
            obs, rew, term, trunc, info = vec.step(np.zeros((2, 1), np.float32))
            assert np.isfinite(rew).all() and not any(info.get("error", ["", ""]))
    finally:
        vec.close()


def test_spec_max_episode_steps_is_the_scenario_horizon(gt, tmp_path):
    import gymnasium

    path, data, gen = gt
    kwargs = dict(data=data, generator=gen)
    env = gymnasium.make(ENV_ID, scenario=path, **kwargs)
    assert env.spec.max_episode_steps == 10 == env.unwrapped.horizon
    env.close()
    short = write_scenario(
        tmp_path,
        {
            "simulation.n_runs": 4,
            "simulation.duration_s": 120.0,
            "generator.epochs": 3,
            "policy.horizon": 6,
        },
    )
    env = gymnasium.make(ENV_ID, scenario=short, **kwargs)
    try:
        assert env.spec.max_episode_steps == 6
        env.reset(seed=0)
        steps, done = 0, False
        while not done:
            _, _, term, trunc, _ = env.step(np.array([0.0], np.float32))
            steps, done = steps + 1, term or trunc
        assert steps == 6
    finally:
        env.close()


def test_normalized_spaces_map_onto_the_bounds(gt):
    path, data, gen = gt
    raw = SectionHiddenEnv(path, data, gen)
    norm = SectionHiddenEnv(path, data, gen, normalize=True)
    try:
        assert (norm.action_space.low, norm.action_space.high) == (-1.0, 1.0)
        check_env(norm, skip_render_check=True)
        # The bank's initial observations' mean and std (the PPO agent's).
        shift, scale = norm.scaling.shift, norm.scaling.scale
        a_min, a_max = raw.core.sc.bounds.accel_mps2
        dt = raw.core.dt
        for action, accel in ((-1.0, a_min), (1.0, a_max), (0.0, (a_min + a_max) / 2)):
            o_raw, _ = raw.reset(seed=5)
            o_norm, _ = norm.reset(seed=5)
            np.testing.assert_allclose(o_norm, (o_raw - shift) / scale, rtol=1e-5, atol=1e-5)
            assert norm.observation_space.contains(o_norm)
            ego = norm._slots[norm._ego]
            v0 = norm.core.speed[ego]
            norm.step(np.array([action], np.float32))
            v1 = norm.core.speed[ego]
            assert v1 == pytest.approx(max(0.0, v0 + accel * dt), abs=1e-3)
    finally:
        raw.close()
        norm.close()


def test_pettingzoo_env_normalized_passes_parallel_api_test(gt):
    path, data, gen = gt
    env = SectionHiddenParallelEnv(path, data, gen, normalize=True)
    try:
        assert env.action_space("hidden_0").high[0] == 1.0
        parallel_api_test(env, num_cycles=30)
    finally:
        env.close()

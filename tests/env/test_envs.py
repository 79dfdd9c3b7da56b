"""The public environments pass the official gymnasium and PettingZoo checkers."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import write_scenario
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

from macromicro_sumo import cli
from macromicro_sumo.env.ring_envs import RingHiddenEnv, RingHiddenParallelEnv
from macromicro_sumo.env.wrappers import ENV_ID
from macromicro_sumo.errors import UserError


@pytest.fixture(scope="module")
def gt(tmp_path_factory):
    folder = tmp_path_factory.mktemp("envs")
    path = write_scenario(
        folder, {"simulation.n_runs": 4, "simulation.duration_s": 120.0, "generator.epochs": 3}
    )
    out = folder / "gt"
    assert cli.main(["simulate", str(path), "--out", str(out), "--quiet"]) == 0
    assert (
        cli.main(
            [
                "train-generator",
                str(path),
                "--data",
                str(out),
                "--out",
                str(folder / "gen"),
                "--quiet",
            ]
        )
        == 0
    )
    return path, out, folder / "gen" / "generator.pt"


def test_gymnasium_env_passes_check_env(gt):
    path, data, gen = gt
    env = RingHiddenEnv(path, data, gen)
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
    env = RingHiddenParallelEnv(path, data, gen, hidden=(1, 4))
    try:
        parallel_api_test(env, num_cycles=50)
    finally:
        env.close()


def test_bad_actions_name_the_agent(gt):
    path, data, gen = gt
    env = RingHiddenParallelEnv(path, data, gen, hidden=2)
    try:
        env.reset(seed=0)
        with pytest.raises(ValueError, match="agent hidden_1: action must be finite"):
            env.step({"hidden_0": np.array([0.0]), "hidden_1": np.array([np.nan])})
        with pytest.raises(ValueError, match="agent hidden_0: action must have shape"):
            env.step({"hidden_0": np.zeros(3), "hidden_1": np.array([0.0])})
    finally:
        env.close()


def test_second_env_in_one_process_is_refused_clearly(gt):
    path, data, gen = gt
    first = RingHiddenEnv(path, data, gen)
    first.reset(seed=0)
    second = RingHiddenEnv(path, data, gen)
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
    env = RingHiddenParallelEnv(path, data, gen, hidden=3)
    try:
        _, infos = env.reset(seed=0)
        assert len({id(i) for i in infos.values()}) == len(infos) == 3
        _, _, _, _, infos = env.step({a: np.array([0.0]) for a in env.agents})
        infos["hidden_0"]["terminal_observation"] = "only hidden_0's"
        assert all("terminal_observation" not in infos[a] for a in ("hidden_1", "hidden_2"))
    finally:
        env.close()


def test_info_counts_the_safety_layers_caps(gt):
    """``info["safety_capped"]``: this step's capped hidden commands, 0 at a reset; summed,
    the core's count. On the paper's ring (spacings ~125 m) even full throttle for a whole
    episode leaves the layer idle: it binds where the ring is dense (test_ring_collisions)."""
    path, data, gen = gt
    env = RingHiddenEnv(path, data, gen)
    try:
        assert env.core.safety == "sumo"  # the default
        total, steps = 0, 0
        for seed in range(3):
            _, info = env.reset(seed=seed)
            assert info["safety_capped"] == 0
            done = False
            while not done:
                _, _, term, trunc, info = env.step(np.array([env.action_space.high[0]]))
                assert info["safety_capped"] in (0, 1)
                total, steps, done = total + info["safety_capped"], steps + 1, term or trunc
        assert total == env.core.safety_capped == 0 and env.core.hidden_steps == steps
        assert not term  # no collision under the layer
    finally:
        env.close()


def test_render_mode_none_is_accepted_and_possible_agents_fit_the_bank(gt):
    path, data, gen = gt
    env = RingHiddenParallelEnv(path, data, gen, hidden=(1, 2), render_mode=None)
    try:
        assert env.render_mode is None and len(env.possible_agents) == 2
        for seed in range(4):
            env.reset(seed=seed)
            assert set(env.agents) <= set(env.possible_agents)
    finally:
        env.close()
    with pytest.raises(ValueError, match="render_mode 'human' is not supported"):
        RingHiddenEnv(path, data, gen, render_mode="human")


def test_supersuit_vector_wrapper_without_adapters(gt):
    """SuperSuit's PettingZoo -> vector env conversion (what SB3 users call) steps as is."""
    import supersuit as ss

    path, data, gen = gt
    env = RingHiddenParallelEnv(path, data, gen, hidden=2)
    vec = ss.pettingzoo_env_to_vec_env_v1(env)
    try:
        obs, infos = vec.reset(seed=0)
        assert obs.shape == (2, env.observation_space("hidden_0").shape[0])
        for _ in range(12):  # past one horizon (10 steps): the auto-reset path runs too
            obs, rew, term, trunc, infos = vec.step(np.zeros((2, 1), np.float32))
            assert obs.shape[0] == 2 and np.isfinite(rew).all()
    finally:
        env.close()


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
    first = RingHiddenEnv(path, data, gen)
    second = RingHiddenEnv(path, data, gen)
    try:
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
    from macromicro_sumo.env.observation import shift_scale

    path, data, gen = gt
    raw = RingHiddenEnv(path, data, gen)
    norm = RingHiddenEnv(path, data, gen, normalize=True)
    try:
        assert (norm.action_space.low, norm.action_space.high) == (-1.0, 1.0)
        check_env(norm, skip_render_check=True)
        shift, scale = shift_scale(raw.core.sc.policy.observation)
        a_min, a_max = raw.core.sc.bounds.accel_mps2
        dt = raw.core.dt
        for action, accel in ((-1.0, a_min), (1.0, a_max), (0.0, (a_min + a_max) / 2)):
            o_raw, _ = raw.reset(seed=5)
            o_norm, _ = norm.reset(seed=5)
            np.testing.assert_allclose(o_norm, (o_raw - shift) / scale, rtol=1e-5, atol=1e-5)
            assert norm.observation_space.contains(o_norm)
            v0 = norm.core.speed[norm.core.hidden][0]
            norm.step(np.array([action], np.float32))
            v1 = norm.core.speed[norm.core.hidden][0]
            assert v1 == pytest.approx(max(0.0, v0 + accel * dt), abs=1e-3)
    finally:
        raw.close()
        norm.close()


def test_pettingzoo_env_normalized_passes_parallel_api_test(gt):
    path, data, gen = gt
    env = RingHiddenParallelEnv(path, data, gen, hidden=(1, 3), normalize=True)
    try:
        assert env.action_space("hidden_0").high[0] == 1.0
        parallel_api_test(env, num_cycles=30)
    finally:
        env.close()

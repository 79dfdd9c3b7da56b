"""gymnasium.make("macromicro/RingHidden-v0") with no arguments: the demo is built into the
cache on first use, said on stderr, and reused afterwards."""

from __future__ import annotations

import time

import gymnasium
import numpy as np
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

from macromicro_sumo.env.examples import cache_root
from macromicro_sumo.env.section_envs import SectionHiddenParallelEnv
from macromicro_sumo.env.wrappers import ENV_ID


def test_no_argument_make_builds_the_demo_once(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MACROMICRO_CACHE", str(tmp_path / "cache"))
    assert cache_root() == tmp_path / "cache"
    t0 = time.perf_counter()
    env = gymnasium.make(ENV_ID)
    built_s = time.perf_counter() - t0
    err = capsys.readouterr().err
    assert "first use of the demo" in err and "demo built in" in err
    assert str(tmp_path / "cache") in err
    try:
        assert env.spec.max_episode_steps == 10
        obs, info = env.reset(seed=0)
        assert obs.shape == env.observation_space.shape
        _, r, _, _, info = env.step(np.array([0.0], np.float32))
        assert 0.0 < r <= 1.0 and not info["error"]
        check_env(env.unwrapped, skip_render_check=True)  # its second env reads the cache
        env.reset(seed=1)
    finally:
        env.close()
    t0 = time.perf_counter()
    again = gymnasium.make(ENV_ID, normalize=True)
    try:
        assert time.perf_counter() - t0 < built_s
        assert "first use" not in capsys.readouterr().err  # reused, not rebuilt
        assert again.action_space.high[0] == 1.0
    finally:
        again.close()
    # Vectorised: every sub-env in one SUMO run, from the same cache.
    vec = gymnasium.make_vec(ENV_ID, num_envs=4, vectorization_mode="vector_entry_point")
    try:
        obs, _ = vec.reset(seed=0)
        assert obs.shape == (4, *env.observation_space.shape)
        _, r, _, _, _ = vec.step(np.zeros((4, 1), np.float32))
        assert r.shape == (4,) and ((r > 0.0) & (r <= 1.0)).all()
    finally:
        vec.close()
    env = SectionHiddenParallelEnv()  # PettingZoo: the demo too
    try:
        parallel_api_test(env, num_cycles=20)
    finally:
        env.close()


def test_supersuit_vector_wrapper_on_a_fixed_hidden_count():
    """SuperSuit's PettingZoo -> vector env conversion (what SB3 users call) steps as is
    where every episode hides the same number of vehicles (``hidden=``, the demo ring)."""
    import pytest
    import supersuit as ss

    from macromicro_sumo.errors import UserError

    env = SectionHiddenParallelEnv(hidden=2)
    vec = ss.pettingzoo_env_to_vec_env_v1(env)
    try:
        assert env.possible_agents == ["hidden_0", "hidden_1"]
        obs, infos = vec.reset(seed=0)
        assert obs.shape == (2, env.observation_space("hidden_0").shape[0])
        for _ in range(12):  # past one horizon (10 steps): the auto-reset path runs too
            obs, rew, term, trunc, infos = vec.step(np.zeros((2, 1), np.float32))
            assert obs.shape[0] == 2 and np.isfinite(rew).all()
    finally:
        env.close()
    with pytest.raises(UserError, match=r"hidden = 99: no scene of the train bank .*\(accepted: "):
        SectionHiddenParallelEnv(hidden=99)

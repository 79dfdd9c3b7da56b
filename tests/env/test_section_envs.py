"""The public section envs (gymnasium and PettingZoo over SectionCore) pass the official
checkers on a small corridor that netgen draws, and come back after check_env's second env."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

from macromicro_sumo.env.section_envs import SectionHiddenEnv, SectionHiddenParallelEnv
from macromicro_sumo.env.wrappers import ENV_ID, SECTION_ENV_ID
from macromicro_sumo.errors import UserError


@pytest.fixture(scope="module")
def section(netgen_corridor):
    """A corridor from netgen with a short ground truth and a briefly trained generator."""
    return netgen_corridor["scenario"], netgen_corridor["gt"], netgen_corridor["gen"]


def test_gymnasium_section_env_passes_check_env_and_lives_on(section):
    path, data, gen = section
    env = gymnasium.make(SECTION_ENV_ID, scenario=path, data=data, generator=gen)
    try:
        assert env.spec.max_episode_steps == 8
        check_env(env.unwrapped, skip_render_check=True)  # builds and closes a second env
        obs, info = env.reset(seed=0)
        assert env.observation_space.contains(obs)
        steps, done = 0, False
        while not done:
            obs, r, term, trunc, info = env.step(np.array([0.0], np.float32))
            assert not info["error"] and 0.0 <= r <= 1.0
            steps, done = steps + 1, term or trunc
        assert steps == 8 or info["left_section"] or info["collision"]
    finally:
        env.close()


def test_gymnasium_section_env_normalized_and_others(section):
    path, data, gen = section
    seen = []

    def others(obs):
        seen.append(obs.shape)
        return np.zeros(len(obs))

    env = SectionHiddenEnv(path, data, gen, normalize=True, others=others)
    try:
        assert (env.action_space.low[0], env.action_space.high[0]) == (-1.0, 1.0)
        check_env(env, skip_render_check=True)
        obs, _ = env.reset(seed=1)
        env.step(np.array([1.0], np.float32))
        k = int(env.core.hidden.sum())
        assert seen[-1][0] == k - 1
    finally:
        env.close()


def test_pettingzoo_section_env_passes_parallel_api_test(section):
    path, data, gen = section
    for normalize in (False, True):
        env = SectionHiddenParallelEnv(path, data, gen, normalize=normalize)
        try:
            assert len(env.possible_agents) == int(env.core.bank.hidden.sum(axis=1).max())
            parallel_api_test(env, num_cycles=40)
        finally:
            env.close()


def test_pettingzoo_section_agents_are_the_hidden_vehicles(section):
    path, data, gen = section
    env = SectionHiddenParallelEnv(path, data, gen, seed=3)
    try:
        for seed in range(3):
            obs, infos = env.reset(seed=seed)
            assert len(env.agents) == int(env.core.hidden.sum())
            while env.agents:
                live = list(env.agents)
                obs, rew, term, trunc, infos = env.step({a: np.zeros(1) for a in live})
                assert set(obs) == set(live)
                for a in live:
                    if infos[a]["left_section"]:
                        assert term[a] and a not in env.agents
    finally:
        env.close()


def test_both_ids_make_the_section_env(section):
    """``macromicro/RingHidden-v0`` (the ring wing's env until stop 25) is the same env."""
    path, data, gen = section
    assert gymnasium.spec(ENV_ID).entry_point == gymnasium.spec(SECTION_ENV_ID).entry_point
    env = gymnasium.make(ENV_ID, scenario=path, data=data, generator=gen)
    try:
        assert isinstance(env.unwrapped, SectionHiddenEnv)
    finally:
        env.close()
    with pytest.raises(UserError, match="pass scenario= too"):
        SectionHiddenEnv(None, data, gen)

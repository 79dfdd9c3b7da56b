"""gymnasium.make("macromicro/RingHidden-v0") with no arguments: the demo is built into the
cache on first use, said on stderr, and reused afterwards."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np
import pandas as pd
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

from macromicro_sumo.env import examples
from macromicro_sumo.env.examples import cache_root
from macromicro_sumo.env.section_envs import SectionHiddenParallelEnv
from macromicro_sumo.env.wrappers import ENV_ID
from macromicro_sumo.errors import UserError

# The shipped demo budget (examples.DEMO_OVERRIDES: 20 runs of 180 s, a generator of 200
# epochs) takes 45 s of CPU to build, 30 of them in the generator; what these tests check
# (built once into the cache, said on stderr, reused; its envs pass the API checkers) does
# not depend on the budget: 4 runs of 120 s and 10 epochs build in about 5 s. The shipped
# budget is built by test_the_shipped_demo_builds_and_steps (slow).
SMALL_DEMO = {"simulation.n_runs": 4, "simulation.duration_s": 120.0, "generator.epochs": 10}


@pytest.fixture
def small_demo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A demo of ``SMALL_DEMO``'s budget, cached under ``tmp_path`` (not the user's cache)."""
    monkeypatch.setattr(examples, "DEMO_OVERRIDES", SMALL_DEMO)
    monkeypatch.setenv("MACROMICRO_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_no_argument_make_builds_the_demo_once(small_demo, capsys):
    assert cache_root() == small_demo
    env = gymnasium.make(ENV_ID)
    err = capsys.readouterr().err
    assert "first use of the demo" in err and "demo built in" in err
    assert str(small_demo) in err
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
    (folder,) = [p for p in small_demo.iterdir() if p.is_dir()]
    written = {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}
    assert folder / "ground_truth" / "trajectories.csv" in written
    again = gymnasium.make(ENV_ID, normalize=True)
    try:
        assert "first use" not in capsys.readouterr().err  # reused, not rebuilt
        assert {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()} == written
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


def test_supersuit_vector_wrapper_on_a_fixed_hidden_count(small_demo):
    """SuperSuit's PettingZoo -> vector env conversion (what SB3 users call) steps as is
    where every episode hides the same number of vehicles (``hidden=``, the demo ring)."""
    import supersuit as ss

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


@pytest.mark.slow  # about 45 s of CPU: 20 runs of 180 s and a generator of 200 epochs
def test_the_shipped_demo_builds_and_steps(tmp_path, monkeypatch, capsys):
    """The demo with its shipped budget (what a user's first ``gymnasium.make`` builds)."""
    monkeypatch.setenv("MACROMICRO_CACHE", str(tmp_path / "cache"))
    env = gymnasium.make(ENV_ID)
    try:
        assert "demo built in" in capsys.readouterr().err
        runs = pd.read_csv(examples.demo().data / "runs.csv")
        assert len(runs) == examples.DEMO_OVERRIDES["simulation.n_runs"]
        assert (runs["collisions"] == 0).all()
        obs, _ = env.reset(seed=0)
        assert obs.shape == env.observation_space.shape
        _, r, _, _, info = env.step(np.array([0.0], np.float32))
        assert 0.0 < r <= 1.0 and not info["error"]
    finally:
        env.close()

"""Off-the-shelf RL on the public env: Stable-Baselines3's PPO with its default settings
learns on ``normalize=True`` (slow: ``make test-slow``)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from conftest import write_scenario

from macromicro_sumo import cli
from macromicro_sumo.env.wrappers import ENV_ID

# Enough runs that the bank holds a few hundred episodes; a generator trained to its stop.
DATA = {"simulation.n_runs": 20, "simulation.duration_s": 180.0, "generator.epochs": 200}
TRAIN_STEPS = 60_000  # 6,000 episodes of H = 10 steps; about a minute
EPISODES = 200


def mean_return(env: gymnasium.Env, act, episodes: int = EPISODES) -> float:
    """Mean undiscounted return over the episodes that resets with seeds 10_000... draw."""
    returns = []
    for i in range(episodes):
        obs, _ = env.reset(seed=10_000 + i)
        done, total = False, 0.0
        while not done:
            obs, r, term, trunc, _ = env.step(act(obs))
            total += r
            done = term or trunc
        returns.append(total)
    return float(np.mean(returns))


@pytest.mark.slow
def test_sb3_ppo_with_default_settings_beats_constant_zero_acceleration(tmp_path):
    from stable_baselines3 import PPO

    path = write_scenario(tmp_path, DATA)
    data, gen = tmp_path / "gt", tmp_path / "gen"
    assert cli.main(["simulate", str(path), "--out", str(data), "--quiet"]) == 0
    args = ["train-generator", str(path), "--data", str(data), "--out", str(gen), "--quiet"]
    assert cli.main(args) == 0
    torch.set_num_threads(1)
    env = gymnasium.make(
        ENV_ID, scenario=path, data=data, generator=gen / "generator.pt", normalize=True
    )
    try:
        core = env.unwrapped.core
        a_min, a_max = core.a_min, core.a_max
        zero = np.array([2 * (0.0 - a_min) / (a_max - a_min) - 1], np.float32)  # 0 m/s^2
        constant = mean_return(env, lambda obs: zero)
        model = PPO("MlpPolicy", env, seed=0, verbose=0)
        model.learn(TRAIN_STEPS)
        learned = mean_return(env, lambda obs: model.predict(obs, deterministic=True)[0])
    finally:
        env.close()
    print(f"SB3 PPO {learned:.3f} vs constant zero acceleration {constant:.3f}")
    assert learned > constant

"""The public environments over the SUMO ring: ``RingHiddenEnv`` (gymnasium, one hidden
vehicle) and ``RingHiddenParallelEnv`` (PettingZoo, K hidden vehicles, one shared policy),
both wrapping ``env.RingCore``; ``make_ring_hidden_env`` is ``gymnasium.make``'s entry point
for ``macromicro/RingHidden-v0``. Spaces, rewards and arguments: ``env/wrappers.py``'s
docstring.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit
from pettingzoo import ParallelEnv

from macromicro_sumo.data.ring import load_ground_truth, split_runs
from macromicro_sumo.env.examples import demo
from macromicro_sumo.env.ring import EpisodeBank, RingCore, build_bank, generator_completion
from macromicro_sumo.env.wrappers import (
    ENV_ID,
    SECTION_ENV_ID,
    Scaling,
    check_action,
    check_render_mode,
    refuse_in_process_vector,
    step_info,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.ring_train import load_generator
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.scenario.section import SectionScenario


def make_bank(
    scenario: str | Path | Scenario | None,
    data: str | Path | None,
    generator: str | Path | None,
    split: str = "train",
    hidden: int | tuple[int, int] = 1,
    seed: int = 0,
) -> tuple[Scenario, EpisodeBank]:
    """The ring's episodes; ``scenario=None`` (and no ``data`` or ``generator``): the demo
    (``env.examples.demo``, built into the cache on first use)."""
    if scenario is None:
        if data is not None or generator is not None:
            raise UserError("data and generator go with a scenario; pass scenario= too")
        built = demo()
        scenario, data, generator = built.scenario, built.data, built.generator
    elif data is None:
        raise UserError("a scenario needs its ground truth: pass data= (from macromicro simulate)")
    sc = scenario if isinstance(scenario, Scenario | SectionScenario) else load_scenario(scenario)
    if isinstance(sc, SectionScenario):
        raise UserError(
            f"{sc.source}: a section scenario; its envs are {SECTION_ENV_ID} and "
            "SectionHiddenParallelEnv"
        )
    gt = load_ground_truth(data, sc)
    runs = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)[split]
    if generator is None:
        fn = lambda s: (s.arc_m, s.speed_mps)  # noqa: E731 - the true hidden states
    else:
        fn = generator_completion(load_generator(generator, sc), sc, seed)
    return sc, build_bank(sc, gt, runs, fn, hidden, seed)


class RingHiddenEnv(gym.Env):
    """Gymnasium env: one hidden vehicle on the SUMO ring (see the module docstring)."""

    metadata = {"render_modes": []}

    def __init__(
        self,
        scenario: str | Path | Scenario | None = None,
        data: str | Path | None = None,
        generator: str | Path | None = None,
        split: str = "train",
        seed: int = 0,
        render_mode: str | None = None,
        normalize: bool = False,
    ) -> None:
        check_render_mode(render_mode)
        refuse_in_process_vector(ENV_ID)
        self.render_mode = render_mode
        sc, bank = make_bank(scenario, data, generator, split, 1, seed)
        self.core = RingCore(sc, bank, seed=seed)
        self.horizon = sc.policy.horizon
        self.scaling = Scaling(
            sc.bounds.accel_mps2, sc.policy.observation, self.core.length, normalize
        )
        self.action_space = self.scaling.action_space
        self.observation_space = self.scaling.observation_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs = self.core.reset(int(self.np_random.integers(len(self.core.bank))))
        return self.scaling.obs(obs[self.core.hidden][0]), step_info(self.core)

    def step(self, action):
        a = self.scaling.accel(check_action("hidden_0", action))
        res = self.core.step(np.array([a]))
        truncated = res.truncated or self.core.t >= self.horizon
        obs = self.scaling.obs(res.obs[self.core.hidden][0])
        return (
            obs,
            float(res.r_macro),
            bool(res.collision),
            bool(truncated),
            step_info(self.core, res),
        )

    def close(self) -> None:
        self.core.close()


class RingHiddenParallelEnv(ParallelEnv):
    """PettingZoo parallel env: K hidden vehicles, one shared policy (module docstring)."""

    metadata = {"name": "macromicro_ring_hidden_v0", "render_modes": []}

    def __init__(
        self,
        scenario: str | Path | Scenario | None = None,
        data: str | Path | None = None,
        generator: str | Path | None = None,
        split: str = "train",
        hidden: int | tuple[int, int] = (1, 4),
        seed: int = 0,
        render_mode: str | None = None,
        normalize: bool = False,
    ) -> None:
        check_render_mode(render_mode)
        self.render_mode = render_mode
        sc, bank = make_bank(scenario, data, generator, split, hidden, seed)
        self.core = RingCore(sc, bank, seed=seed)
        self.horizon = sc.policy.horizon
        # As many agents as the most hidden vehicles any episode of the bank has.
        most = int(bank.hidden.sum(axis=1).max())
        self.possible_agents = [f"hidden_{i}" for i in range(most)]
        self.agents: list[str] = []
        self.scaling = Scaling(
            sc.bounds.accel_mps2, sc.policy.observation, self.core.length, normalize
        )
        self._act, self._obs = self.scaling.action_space, self.scaling.observation_space
        self._rng = np.random.default_rng(seed)

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs

    def action_space(self, agent: str) -> spaces.Box:
        return self._act

    def _split(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        hidden = self.scaling.obs(obs[self.core.hidden])
        return dict(zip(self.agents, hidden, strict=True))

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        obs = self.core.reset(int(self._rng.integers(len(self.core.bank))))
        self.agents = self.possible_agents[: int(self.core.hidden.sum())]
        info = step_info(self.core)
        return self._split(obs), {a: dict(info) for a in self.agents}

    def step(self, actions: dict[str, Any]):
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"agent {missing[0]}: no action given")
        acc = np.array([self.scaling.accel(check_action(a, actions[a])) for a in self.agents])
        res = self.core.step(acc)
        truncated = res.truncated or self.core.t >= self.horizon
        obs = self._split(res.obs)
        info = step_info(self.core, res)
        agents = list(self.agents)
        out = (
            obs,
            {a: float(res.r_macro) for a in agents},
            {a: bool(res.collision) for a in agents},
            {a: bool(truncated) for a in agents},
            # One dict per agent: wrappers (SuperSuit) write each agent's final observation
            # into its info, and a shared dict would hand every agent the last one's.
            {a: dict(info) for a in agents},
        )
        if res.collision or truncated:
            self.agents = []
        return out

    def close(self) -> None:
        self.core.close()


def make_ring_hidden_env(**kwargs: Any) -> gym.Env:
    """``gymnasium.make``'s entry point: a ``RingHiddenEnv`` in a ``TimeLimit`` of its
    scenario's horizon, so that ``env.spec.max_episode_steps`` is that scenario's H (the
    registry cannot know it: the scenario is an argument)."""
    env = RingHiddenEnv(**kwargs)
    return TimeLimit(env, env.horizon)

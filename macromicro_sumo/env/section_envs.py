"""The public environments over a section of a network (the paper's ring among them):
``SectionHiddenEnv`` (gymnasium, one hidden vehicle; the others apply ``others``) and
``SectionHiddenParallelEnv`` (PettingZoo, every hidden vehicle, one shared policy), both
wrapping ``env.SectionCore``; ``make_section_hidden_env`` is ``gymnasium.make``'s entry
point for ``macromicro/SectionHidden-v0`` and ``macromicro/RingHidden-v0``. With no
``scenario`` and ``data`` they run the demo (``env.examples.demo``). Spaces, rewards and
arguments: ``env/wrappers.py``'s docstring.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit
from pettingzoo import ParallelEnv

from macromicro_sumo.data.section import SectionSnapshots, section_snapshots, split_runs
from macromicro_sumo.env.examples import demo
from macromicro_sumo.env.observation import bank_shift_scale
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import (
    SectionBank,
    build_section_bank,
    recorded_min_gap,
    typical_length,
    typical_vclass,
)
from macromicro_sumo.env.section_observations import initial_observations
from macromicro_sumo.env.wrappers import (
    SECTION_ENV_ID,
    Scaling,
    check_action,
    check_render_mode,
    refuse_in_process_vector,
    step_info,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.section_sampler import (
    generator_completion as section_completion,
)
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import SectionTruth, load_section_truth


def true_section_completion(snaps: SectionSnapshots):
    """``build_section_bank``'s completion with the true hidden vehicles (no generator)."""
    key = np.where(snaps.valid, np.where(snaps.observed, 0, 1), 2)
    order = np.argsort(key, axis=1, kind="stable")  # observed first, then the hidden

    def take(a: np.ndarray) -> np.ndarray:
        return np.take_along_axis(a, order, 1)

    return (
        take(snaps.lane),
        take(snaps.arc_m),
        take(snaps.speed_mps),
        take(snaps.valid),
        take(snaps.hidden),
    )


def make_section_bank(
    scenario: str | Path | SectionScenario | None,
    data: str | Path | None,
    generator: str | Path | None,
    split: str = "train",
    seed: int = 0,
) -> tuple[SectionScenario, SectionTruth, SectionBank]:
    """Episodes of a section's ``split`` runs that have a hidden vehicle, completed by the
    generator (``None``: the true hidden vehicles). ``scenario=None`` (and no ``data`` or
    ``generator``): the demo (``env.examples.demo``, built into the cache on first use)."""
    if scenario is None:
        if data is not None or generator is not None:
            raise UserError("data and generator go with a scenario; pass scenario= too")
        built = demo()
        scenario, data, generator = built.scenario, built.data, built.generator
    elif data is None:
        raise UserError("a scenario needs its ground truth: pass data= (from macromicro simulate)")
    sc = scenario if isinstance(scenario, SectionScenario) else load_scenario(scenario)
    truth = load_section_truth(data, sc)
    runs = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)[split]
    snaps = section_snapshots(truth, sc, runs)
    if generator is None:
        complete = true_section_completion
    else:
        net = load_section_generator(generator, sc)
        k_source, length = sc.generator.k_source, typical_length(truth)
        complete = section_completion(net, truth.section, sc, k_source, seed, length)
    bank = build_section_bank(sc, truth, snaps, complete, sc.policy.horizon, seed)
    keep = np.flatnonzero(bank.hidden.any(axis=1))
    if keep.size == 0:
        raise UserError(f"{data}: no episode of the {split!r} runs has a hidden vehicle")
    return sc, truth, bank.take(keep)


def _section_setup(
    scenario, data, generator, split: str, seed: int, normalize: bool
) -> tuple[SectionCore, Scaling]:
    sc, truth, bank = make_section_bank(scenario, data, generator, split, seed)
    net_file = scenario_inputs(sc).net_file
    core = SectionCore(
        sc,
        truth.section,
        bank,
        net_file,
        seed=seed,
        vclass=typical_vclass(truth),
        replay_min_gap_m=recorded_min_gap(truth),
    )
    reach = max(float(truth.section.length_m), NO_LEADER_GAP_M)
    fitted = bank_shift_scale(initial_observations(sc, truth.section, bank)) if normalize else None
    scaling = Scaling(sc.bounds.accel_mps2, sc.policy.observation, reach, normalize, fitted)
    return core, scaling


class SectionHiddenEnv(gym.Env):
    """Gymnasium env: one hidden vehicle on a section of a user's network (module
    docstring, "Sections"); the other hidden vehicles apply ``others``."""

    metadata = {"render_modes": []}

    def __init__(
        self,
        scenario: str | Path | SectionScenario | None = None,
        data: str | Path | None = None,
        generator: str | Path | None = None,
        split: str = "train",
        seed: int = 0,
        render_mode: str | None = None,
        normalize: bool = False,
        others: float | Callable[[np.ndarray], np.ndarray] = 0.0,
    ) -> None:
        check_render_mode(render_mode)
        refuse_in_process_vector(SECTION_ENV_ID)
        self.render_mode = render_mode
        self.core, self.scaling = _section_setup(scenario, data, generator, split, seed, normalize)
        self.horizon = self.core.sc.policy.horizon
        self.others = others
        self.action_space = self.scaling.action_space
        self.observation_space = self.scaling.observation_space
        self._slots = np.zeros(0, dtype=np.int64)
        self._ego = 0  # index of the agent's vehicle among the episode's hidden slots

    def _obs(self, obs: np.ndarray) -> np.ndarray:
        return self.scaling.obs(obs[self._slots[self._ego]])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs = self.core.reset(int(self.np_random.integers(len(self.core.bank))))
        self._slots = np.flatnonzero(self.core.hidden)
        self._ego = int(self.np_random.integers(len(self._slots)))
        self._raw = obs
        return self._obs(obs), step_info(self.core)

    def _others_accel(self) -> np.ndarray:
        rest = np.delete(self._slots, self._ego)
        if callable(self.others):
            acc = np.asarray(self.others(self._raw[rest]), dtype=np.float64).reshape(-1)
            if acc.shape != (len(rest),):
                raise ValueError(f"others returned {acc.shape[0]} accelerations for {len(rest)}")
            return acc
        return np.full(len(rest), float(self.others))

    def step(self, action):
        a = self.scaling.accel(check_action("hidden_0", action))
        acc = np.insert(self._others_accel(), self._ego, a)
        res = self.core.step(acc)
        self._raw = res.obs
        left = not res.active[self._slots[self._ego]]
        terminated = bool(res.collision) or left
        truncated = not terminated and (res.truncated or self.core.t >= self.horizon)
        info = step_info(self.core, res)
        info["left_section"] = left
        return self._obs(res.obs), float(res.r_macro), terminated, bool(truncated), info

    def close(self) -> None:
        self.core.close()


class SectionHiddenParallelEnv(ParallelEnv):
    """PettingZoo parallel env: the hidden vehicles of a section, one shared policy (module
    docstring, "Sections")."""

    metadata = {"name": "macromicro_section_hidden_v0", "render_modes": []}

    def __init__(
        self,
        scenario: str | Path | SectionScenario | None = None,
        data: str | Path | None = None,
        generator: str | Path | None = None,
        split: str = "train",
        seed: int = 0,
        render_mode: str | None = None,
        normalize: bool = False,
        hidden: int | None = None,
    ) -> None:
        check_render_mode(render_mode)
        self.render_mode = render_mode
        self.core, self.scaling = _section_setup(scenario, data, generator, split, seed, normalize)
        self.horizon = self.core.sc.policy.horizon
        counts = self.core.bank.hidden.sum(axis=1)
        # ``hidden``: only the scenes that hide that many vehicles, so that every episode has
        # the same agents (SuperSuit's vector wrappers need a fixed number; on a closed
        # section nobody leaves, so they stay until the episode ends).
        self._scenes = np.arange(len(counts))
        if hidden is not None:
            self._scenes = np.flatnonzero(counts == hidden)
            if not len(self._scenes):
                have = ", ".join(str(int(k)) for k in np.unique(counts))
                raise UserError(
                    f"SectionHiddenParallelEnv: hidden = {hidden}: no scene of the {split} "
                    f"bank hides that many vehicles (accepted: {have})"
                )
        most = int(counts[self._scenes].max())
        self.possible_agents = [f"hidden_{i}" for i in range(most)]
        self.agents: list[str] = []
        self._act, self._obs = self.scaling.action_space, self.scaling.observation_space
        self._rng = np.random.default_rng(seed)
        self._slots = np.zeros(0, dtype=np.int64)

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs

    def action_space(self, agent: str) -> spaces.Box:
        return self._act

    def _split(self, obs: np.ndarray, agents: list[str]) -> dict[str, np.ndarray]:
        return {a: self.scaling.obs(obs[self._slots[self._index[a]]]) for a in agents}

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        obs = self.core.reset(int(self._scenes[self._rng.integers(len(self._scenes))]))
        self._slots = np.flatnonzero(self.core.hidden)
        self._index = {f"hidden_{k}": k for k in range(len(self._slots))}
        # A hidden vehicle SUMO could not place is not an agent (the first step truncates).
        self.agents = [a for a, k in self._index.items() if self.core.active[self._slots[k]]]
        info = step_info(self.core)
        return self._split(obs, self.agents), {a: dict(info) for a in self.agents}

    def step(self, actions: dict[str, Any]):
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"agent {missing[0]}: no action given")
        acc = np.zeros(len(self._slots))
        for a in self.agents:
            acc[self._index[a]] = self.scaling.accel(check_action(a, actions[a]))
        res = self.core.step(acc)
        truncated = res.truncated or self.core.t >= self.horizon
        info = step_info(self.core, res)
        agents = list(self.agents)
        on = {a: bool(res.active[self._slots[self._index[a]]]) for a in agents}
        out = (
            self._split(res.obs, agents),
            {a: float(res.r_macro) for a in agents},
            {a: bool(res.collision) or not on[a] for a in agents},
            {a: bool(truncated) for a in agents},
            {a: dict(info, left_section=not on[a]) for a in agents},
        )
        if res.collision or truncated:
            self.agents = []
        else:
            self.agents = [a for a in agents if on[a]]
        return out

    def close(self) -> None:
        self.core.close()


def make_section_hidden_env(**kwargs: Any) -> gym.Env:
    """``gymnasium.make``'s entry point for sections: a ``SectionHiddenEnv`` in a
    ``TimeLimit`` of its scenario's horizon."""
    env = SectionHiddenEnv(**kwargs)
    return TimeLimit(env, env.horizon)

"""Public environments: gymnasium (one hidden vehicle) and PettingZoo (K hidden vehicles,
one shared policy), over the SUMO ring (``RingHiddenEnv``, ``RingHiddenParallelEnv``: wrap
``env.RingCore``) and over a section of a user's network (``SectionHiddenEnv``,
``SectionHiddenParallelEnv``: wrap ``env.SectionCore``; differences under "Sections" below).
Registered with gymnasium as ``macromicro/RingHidden-v0`` and ``macromicro/SectionHidden-v0``
when this module is imported.

## Action Space
Per hidden vehicle: ``Box(a_min, a_max, (1,), float32)``, the longitudinal acceleration
[m/s^2] (``bounds.accel_mps2``, the paper's [-1.1, 0.5]). It is clipped to the bounds and
applied as a speed command v' = max(0, v + a dt) in SUMO speed mode 0. With
``normalize=True``: ``Box(-1, 1, (1,), float32)``, mapped linearly onto [a_min, a_max]
(-1 -> a_min, 1 -> a_max; on the paper's ring 0 is -0.3 m/s^2). A wrong shape or a
NaN/inf raises ``ValueError`` naming the agent.

## Observation Space
Per hidden vehicle: ``Box(4,)`` = [v (m/s), v_limit at its position (m/s), spacing to the
vehicle ahead, front to front (m), v - v_leader (m/s)], from arc positions (the paper's
observation). With ``policy.observation = "lookahead"``: ``Box(6,)``, adding the next
edge's speed limit (m/s) and the distance to it (m). With ``normalize=True`` each feature
is (value - shift) / scale with the fixed per-feature table of ``env.observation.FEATURES``
(the one the ring's PPO agent uses), and the bounds move with it.

## Rewards
r_macro,t = 1 / (1 + lambda_v L_speed,t + lambda_d L_dist,t) on the whole scene
(``macromicro_sumo.data.objective``), the same for every hidden vehicle (the trainer weights
it by eta). The micro term is not a reward:
``info["observed_obs"]`` (M, 4) and ``info["observed_action_mps2"]`` (M,) carry each observed
vehicle's observation in the simulated scene and its recorded action at this step, for the
likelihood term. ``info`` also has ``collision``, ``error`` (a SUMO failure, if any) and the
named terms of ``data.objective``: ``L_speed, L_mean, L_min, L_max, L_var``.

## Starting State
A snapshot of a ground-truth run (the ``split``'s runs) with K hidden vehicles, completed
by the trained generator and placed in SUMO (moved, not re-inserted: SUMO is not restarted).
Observed vehicles replay their recorded speeds.

## Episode End
Truncated after H = ``policy.horizon`` steps of ``simulation.step_length_s`` seconds (10 x
0.5 s on the paper's ring); terminated on a collision (bumper gap below 0); truncated early
with ``info["error"]`` if SUMO fails. ``gymnasium.make`` wraps the env in a ``TimeLimit`` of
H steps, so ``env.spec.max_episode_steps`` is the scenario's H.

## Arguments
``scenario`` (TOML path), ``data`` (ground-truth folder), ``generator`` (generator.pt, or
``None`` to start from the true hidden states), ``split`` ("train", "val", "held_out"),
``hidden`` (K, or a (low, high) range; gymnasium: 1), ``seed``, ``normalize`` (False:
SI units; True: actions in [-1, 1] and normalised observations, for off-the-shelf RL
libraries such as Stable-Baselines3), ``render_mode`` (None only). The ring envs with no
``scenario``, ``data`` and ``generator`` run the demo: the shipped ``ring_paper`` scenario
with 20 runs, whose ground truth and generator are built once (about 10 s, seeded) into a
per-user cache folder (``env.examples``; said on stderr), so that
``gymnasium.make("macromicro/RingHidden-v0")`` works as is.

## Sections
The scenario is a section of a user's network (``[network] kind = "sumo"``), the ground
truth ``macromicro simulate``'s, the generator ``train-generator``'s (``None``: the true
hidden vehicles). Each episode has its own hidden count K (``generator.k_source``);
episodes without a hidden vehicle are left out. Vehicles change lanes (SUMO's model) and
leave an open section. Observations as ``env.SectionCore``'s (spacing ``NO_LEADER_GAP_M``
= 250 m and delta_v 0 with no leader ahead on the lane; zeros once off the section); with
``normalize=True`` the shift and scale are the mean and std of the bank's initial
observations (another road than the ring's), the section PPO agent's. PettingZoo: agents
``hidden_0 .. hidden_{K-1}``; an agent whose vehicle leaves the section is terminated and
drops out. Gymnasium: the agent drives one hidden vehicle drawn at each reset; the others
apply ``others`` (a constant acceleration [m/s^2], default 0, or a function of their raw
observations (K-1, d) returning K-1 accelerations); the episode terminates when its vehicle
leaves the section or on a collision.

## One SUMO simulation per process
libsumo runs one simulation per process. A second env (or ``gymnasium.utils.env_checker.
check_env``'s, which builds and closes one) takes it over; the first env's ``reset()``
then starts its own run again (a fresh SUMO run of the same network), while its ``step()``
without that reset raises ``UserError``. Vectorise with subprocesses:
``gymnasium.vector.AsyncVectorEnv`` (``gymnasium.make_vec(..., vectorization_mode="async")``)
or Stable-Baselines3's ``SubprocVecEnv``; a ``SyncVectorEnv`` or ``DummyVecEnv`` of more
than one env is refused when it is built.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit
from pettingzoo import ParallelEnv

from macromicro_sumo.data.ring import load_ground_truth, split_runs
from macromicro_sumo.data.section import SectionSnapshots, section_snapshots
from macromicro_sumo.env.examples import demo
from macromicro_sumo.env.observation import bank_shift_scale, feature_names, shift_scale
from macromicro_sumo.env.ring import EpisodeBank, RingCore, build_bank, generator_completion
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import (
    SectionBank,
    build_section_bank,
    initial_observations,
    typical_vclass,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.ring_train import load_generator
from macromicro_sumo.generator.section_sampler import (
    generator_completion as section_completion,
)
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.truth.section import SectionTruth, load_section_truth, scenario_inputs

ENV_ID = "macromicro/RingHidden-v0"
SECTION_ENV_ID = "macromicro/SectionHidden-v0"


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


# Bounds of the raw observation features; "length" is the road's length [m].
_FEATURE_BOUNDS = {
    "speed_mps": (0.0, 100.0),
    "speed_limit_mps": (0.0, 100.0),
    "spacing_m": (0.0, "length"),
    "delta_v_mps": (-100.0, 100.0),
    "next_limit_mps": (0.0, 100.0),
    "dist_to_next_m": (0.0, "length"),
}


class Scaling:
    """The agent's units <-> the core's: actions (m/s^2) and observations (SI), raw or
    normalised (``normalize``; the module docstring's Action and Observation Space)."""

    def __init__(
        self,
        accel_mps2: tuple[float, float],
        observation: str,
        length_m: float,
        normalize: bool,
        shift_scale_: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        self.a_min, self.a_max = (float(a) for a in accel_mps2)
        self.normalize = bool(normalize)
        names = feature_names(observation)
        lo = np.array([_FEATURE_BOUNDS[n][0] for n in names], dtype=np.float64)
        hi = np.array(
            [
                length_m if _FEATURE_BOUNDS[n][1] == "length" else _FEATURE_BOUNDS[n][1]
                for n in names
            ]
        )
        if self.normalize:
            self.shift, self.scale = shift_scale_ or shift_scale(observation)
            lo, hi = (lo - self.shift) / self.scale, (hi - self.shift) / self.scale
            self.action_space = spaces.Box(np.float32(-1), np.float32(1), (1,), np.float32)
        else:
            self.shift, self.scale = np.zeros(len(names)), np.ones(len(names))
            self.action_space = spaces.Box(
                np.float32(self.a_min), np.float32(self.a_max), (1,), np.float32
            )
        self.observation_space = spaces.Box(
            lo.astype(np.float32), hi.astype(np.float32), dtype=np.float32
        )

    def accel(self, action: float) -> float:
        """The acceleration [m/s^2] an action asks for (the core clips it to the bounds)."""
        if not self.normalize:
            return action
        return self.a_min + (action + 1.0) * 0.5 * (self.a_max - self.a_min)

    def obs(self, raw: np.ndarray) -> np.ndarray:
        """Observations (..., d) in the agent's units, float32."""
        if not self.normalize:
            return raw.astype(np.float32)
        return ((raw - self.shift) / self.scale).astype(np.float32)


# Vector envs that step their envs one after the other in this process: (module, class).
_IN_PROCESS_VECTORS = {
    ("gymnasium.vector.sync_vector_env", "SyncVectorEnv"): "gymnasium.vector.SyncVectorEnv",
    ("stable_baselines3.common.vec_env.dummy_vec_env", "DummyVecEnv"): "DummyVecEnv",
}
_SUBPROCESS_HINT = (
    "gymnasium.vector.AsyncVectorEnv (gymnasium.make_vec(..., vectorization_mode='async')) "
    "or stable_baselines3's SubprocVecEnv"
)


def _refuse_in_process_vector(name: str) -> None:
    """Fail while a vector env that would hold several of these envs in this process is
    being built: libsumo runs one simulation per process, so each env's reset would take
    SUMO from the others and their steps would fail."""
    frame = sys._getframe(1)
    while frame is not None:
        owner = frame.f_locals.get("self") if frame.f_code.co_name == "__init__" else None
        cls = type(owner)
        vector = _IN_PROCESS_VECTORS.get((cls.__module__, cls.__name__))
        if vector is not None:
            try:
                n = len(frame.f_locals.get("env_fns", ()))
            except TypeError:  # an iterator of env functions: its length is unknown
                n = 1
            if n > 1:
                raise UserError(
                    f"{vector} would run {n} {name} envs in one process, but libsumo runs one "
                    f"SUMO simulation per process; use {_SUBPROCESS_HINT}: one process per env"
                )
        frame = frame.f_back


def _check_render_mode(render_mode: str | None) -> None:
    if render_mode is not None:
        raise ValueError(f"render_mode {render_mode!r} is not supported; accepted: None")


def _check_action(agent: str, action: Any) -> float:
    a = np.asarray(action, dtype=np.float64)
    if a.shape not in ((1,), ()):
        raise ValueError(f"agent {agent}: action must have shape (1,), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"agent {agent}: action must be finite, got {a.reshape(-1)[0]}")
    return float(a.reshape(-1)[0])


def _info(core: RingCore | SectionCore, res=None) -> dict[str, Any]:
    """The observed vehicles on the road now, their observations and recorded actions (NaN
    where unknown), and the step's outcome and named reward terms."""
    obs = core.observations()
    observed = core.active & ~core.hidden
    t = min(core.t, core.bank.gt_accel_mps2.shape[1] - 1)
    info: dict[str, Any] = {
        "observed_obs": obs[observed].astype(np.float32),
        "observed_action_mps2": core.bank.gt_accel_mps2[core.episode, t][observed],
        "collision": bool(res.collision) if res else False,
        "error": res.error if res else "",
    }
    if res is not None:
        info.update(res.terms)
    return info


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
        _check_render_mode(render_mode)
        _refuse_in_process_vector(ENV_ID)
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
        return self.scaling.obs(obs[self.core.hidden][0]), _info(self.core)

    def step(self, action):
        a = self.scaling.accel(_check_action("hidden_0", action))
        res = self.core.step(np.array([a]))
        truncated = res.truncated or self.core.t >= self.horizon
        obs = self.scaling.obs(res.obs[self.core.hidden][0])
        return obs, float(res.r_macro), bool(res.collision), bool(truncated), _info(self.core, res)

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
        _check_render_mode(render_mode)
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
        info = _info(self.core)
        return self._split(obs), {a: dict(info) for a in self.agents}

    def step(self, actions: dict[str, Any]):
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"agent {missing[0]}: no action given")
        acc = np.array([self.scaling.accel(_check_action(a, actions[a])) for a in self.agents])
        res = self.core.step(acc)
        truncated = res.truncated or self.core.t >= self.horizon
        obs = self._split(res.obs)
        info = _info(self.core, res)
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


# --------------------------------------------------------------------------- sections


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
    scenario: str | Path | SectionScenario,
    data: str | Path,
    generator: str | Path | None,
    split: str = "train",
    seed: int = 0,
) -> tuple[SectionScenario, SectionTruth, SectionBank]:
    """Episodes of a section's ``split`` runs that have a hidden vehicle, completed by the
    generator (``None``: the true hidden vehicles)."""
    sc = scenario if isinstance(scenario, Scenario | SectionScenario) else load_scenario(scenario)
    if not isinstance(sc, SectionScenario):
        raise UserError(
            f"{sc.source}: a ring scenario; its envs are {ENV_ID} and RingHiddenParallelEnv"
        )
    truth = load_section_truth(data, sc)
    runs = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)[split]
    snaps = section_snapshots(truth, sc, runs)
    if generator is None:
        complete = true_section_completion
    else:
        net = load_section_generator(generator, sc)
        complete = section_completion(net, truth.section, sc, sc.generator.k_source, seed)
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
    core = SectionCore(sc, truth.section, bank, net_file, seed=seed, vclass=typical_vclass(truth))
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
        scenario: str | Path | SectionScenario,
        data: str | Path,
        generator: str | Path | None = None,
        split: str = "train",
        seed: int = 0,
        render_mode: str | None = None,
        normalize: bool = False,
        others: float | Callable[[np.ndarray], np.ndarray] = 0.0,
    ) -> None:
        _check_render_mode(render_mode)
        _refuse_in_process_vector(SECTION_ENV_ID)
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
        return self._obs(obs), _info(self.core)

    def _others_accel(self) -> np.ndarray:
        rest = np.delete(self._slots, self._ego)
        if callable(self.others):
            acc = np.asarray(self.others(self._raw[rest]), dtype=np.float64).reshape(-1)
            if acc.shape != (len(rest),):
                raise ValueError(f"others returned {acc.shape[0]} accelerations for {len(rest)}")
            return acc
        return np.full(len(rest), float(self.others))

    def step(self, action):
        a = self.scaling.accel(_check_action("hidden_0", action))
        acc = np.insert(self._others_accel(), self._ego, a)
        res = self.core.step(acc)
        self._raw = res.obs
        left = not res.active[self._slots[self._ego]]
        terminated = bool(res.collision) or left
        truncated = not terminated and (res.truncated or self.core.t >= self.horizon)
        info = _info(self.core, res)
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
        scenario: str | Path | SectionScenario,
        data: str | Path,
        generator: str | Path | None = None,
        split: str = "train",
        seed: int = 0,
        render_mode: str | None = None,
        normalize: bool = False,
    ) -> None:
        _check_render_mode(render_mode)
        self.render_mode = render_mode
        self.core, self.scaling = _section_setup(scenario, data, generator, split, seed, normalize)
        self.horizon = self.core.sc.policy.horizon
        most = int(self.core.bank.hidden.sum(axis=1).max())
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
        obs = self.core.reset(int(self._rng.integers(len(self.core.bank))))
        self._slots = np.flatnonzero(self.core.hidden)
        self._index = {f"hidden_{k}": k for k in range(len(self._slots))}
        # A hidden vehicle SUMO could not place is not an agent (the first step truncates).
        self.agents = [a for a, k in self._index.items() if self.core.active[self._slots[k]]]
        info = _info(self.core)
        return self._split(obs, self.agents), {a: dict(info) for a in self.agents}

    def step(self, actions: dict[str, Any]):
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"agent {missing[0]}: no action given")
        acc = np.zeros(len(self._slots))
        for a in self.agents:
            acc[self._index[a]] = self.scaling.accel(_check_action(a, actions[a]))
        res = self.core.step(acc)
        truncated = res.truncated or self.core.t >= self.horizon
        info = _info(self.core, res)
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


def make_ring_hidden_env(**kwargs: Any) -> gym.Env:
    """``gymnasium.make``'s entry point: a ``RingHiddenEnv`` in a ``TimeLimit`` of its
    scenario's horizon, so that ``env.spec.max_episode_steps`` is that scenario's H (the
    registry cannot know it: the scenario is an argument)."""
    env = RingHiddenEnv(**kwargs)
    return TimeLimit(env, env.horizon)


def make_section_hidden_env(**kwargs: Any) -> gym.Env:
    """``gymnasium.make``'s entry point for sections: a ``SectionHiddenEnv`` in a
    ``TimeLimit`` of its scenario's horizon."""
    env = SectionHiddenEnv(**kwargs)
    return TimeLimit(env, env.horizon)


def register() -> None:
    """Register the gymnasium envs (idempotent): ``gymnasium.make(ENV_ID, scenario=...,
    data=..., generator=...)``, and ``SECTION_ENV_ID`` for a section scenario."""
    for env_id, entry in (
        (ENV_ID, "make_ring_hidden_env"),
        (SECTION_ENV_ID, "make_section_hidden_env"),
    ):
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"macromicro_sumo.env.wrappers:{entry}")


register()

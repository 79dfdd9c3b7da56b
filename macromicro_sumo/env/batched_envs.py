"""``SectionHiddenVectorEnv``: ``num_envs`` gymnasium ``SectionHiddenEnv``s stepped as one
``BatchedSectionCore`` (B scenes in one SUMO run), a gymnasium ``VectorEnv``.

Each sub-env is ``SectionHiddenEnv`` (``env/wrappers.py``'s docstring: spaces, reward,
start, end; one agent vehicle among the scene's hidden ones, the others apply ``others``).
gymnasium's vector envs over ``SectionHiddenEnv`` (``make_vec``) need one process per env
(libsumo runs one simulation per process); this one runs every sub-env in this process and
one simulationStep. Autoreset: gymnasium's next-step mode (the step after an episode's end
starts the sub-env's next episode, its action ignored, reward 0). The batched core takes
closed one-lane sections (the ring): other scenarios get a one-line error.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from macromicro_sumo.env.batched import BatchedSectionCore
from macromicro_sumo.env.observation import bank_shift_scale
from macromicro_sumo.env.section_bank import recorded_min_gap, typical_vclass
from macromicro_sumo.env.section_envs import make_section_bank
from macromicro_sumo.env.section_observations import initial_observations
from macromicro_sumo.env.wrappers import Scaling
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import scenario_inputs


class SectionHiddenVectorEnv(VectorEnv):
    """``num_envs`` one-hidden-vehicle envs of a ring in one SUMO run (module docstring)."""

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 64,
        scenario: str | Path | SectionScenario | None = None,
        data: str | Path | None = None,
        generator: str | Path | None = None,
        split: str = "train",
        seed: int = 0,
        normalize: bool = False,
        others: float | Callable[[np.ndarray], np.ndarray] = 0.0,
    ) -> None:
        if num_envs < 1:
            raise UserError(f"num_envs = {num_envs}: at least 1")
        sc, truth, bank = make_section_bank(scenario, data, generator, split, seed)
        self.core = BatchedSectionCore(
            sc,
            truth.section,
            bank,
            scenario_inputs(sc).net_file,
            num_envs,
            seed=seed,
            replay_min_gap_m=recorded_min_gap(truth),
            vclass=typical_vclass(truth),
        )
        reach = max(float(truth.section.length_m), NO_LEADER_GAP_M)
        fitted = (
            bank_shift_scale(initial_observations(sc, truth.section, bank)) if normalize else None
        )
        self.scaling = Scaling(
            sc.bounds.accel_mps2, sc.policy.observation, reach, normalize, fitted
        )
        self.num_envs = num_envs
        self.others = others
        self.render_mode = None
        self.single_action_space = self.scaling.action_space
        self.single_observation_space = self.scaling.observation_space
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self._rng = np.random.default_rng(seed)
        self._ego = np.zeros(num_envs, dtype=np.int64)  # each sub-env's agent slot
        self._autoreset = np.zeros(num_envs, dtype=bool)
        self._raw = np.zeros((num_envs, self.core.n, self.core.obs_dim))

    def _draw(self, scenes: np.ndarray) -> np.ndarray:
        return np.where(scenes, self._rng.integers(len(self.core.bank), size=self.num_envs), -1)

    def _pick_egos(self, scenes: np.ndarray) -> None:
        for b in np.flatnonzero(scenes):
            slots = np.flatnonzero(self.core.hidden[b])
            self._ego[b] = slots[self._rng.integers(len(slots))]

    def _obs(self) -> np.ndarray:
        return self.scaling.obs(self._raw[np.arange(self.num_envs), self._ego])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        every = np.ones(self.num_envs, dtype=bool)
        self._raw = self.core.reset(self._draw(every))
        self._pick_egos(every)
        self._autoreset[:] = False
        return self._obs(), {}

    def _accels(self, actions: np.ndarray) -> np.ndarray:
        """(B, N) accelerations: the agents' at their slots, ``others`` at the rest."""
        b = np.arange(self.num_envs)
        rest = self.core.hidden.copy()
        rest[b, self._ego] = False
        acc = np.zeros((self.num_envs, self.core.n))
        if callable(self.others):
            got = np.asarray(self.others(self._raw[rest]), dtype=np.float64).reshape(-1)
            if got.shape != (int(rest.sum()),):
                raise ValueError(f"others returned {got.shape[0]} accelerations for {rest.sum()}")
            acc[rest] = got
        else:
            acc[rest] = float(self.others)
        acc[b, self._ego] = self.scaling.accel(actions.reshape(self.num_envs))
        return acc

    def step(self, actions: Any):
        a = np.asarray(actions, dtype=np.float64).reshape(self.num_envs, -1)
        if a.shape[1] != 1 or not np.isfinite(a).all():
            raise ValueError(
                f"actions must be ({self.num_envs}, 1) finite accelerations, got {a.shape}"
            )
        restart = self._autoreset.copy()
        res = self.core.step(self._accels(a), self._draw(restart))
        self._raw = res.obs
        self._pick_egos(restart)
        b = np.arange(self.num_envs)
        left = res.stepped & ~res.active[b, self._ego]
        terminated = res.stepped & (res.collision | left)
        truncated = (
            res.stepped & ~terminated & (res.truncated | (self.core.t >= self.core.bank.horizon))
        )
        self._autoreset = terminated | truncated
        info = {
            "collision": res.collision,
            "left_section": left,
            "error": np.array(res.errors, dtype=object),
            **res.terms,
        }
        reward = np.where(res.stepped, res.r_macro, 0.0)
        return self._obs(), reward, terminated, truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        self.core.close()

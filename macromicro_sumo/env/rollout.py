"""Rollouts: any action function driving the hidden vehicles of every episode of a core."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from macromicro_sumo.env.ring import RingCore

# fn(core, obs (N, 4), rng) -> accelerations of the hidden vehicles (K,)
ActionFn = Callable[[RingCore, np.ndarray, np.random.Generator], np.ndarray]


@dataclass
class Rollouts:
    """Per episode, step (1..H) and vehicle; NaN after an episode ended early."""

    arc_m: np.ndarray
    speed_mps: np.ndarray
    spacing_m: np.ndarray
    accel_mps2: np.ndarray
    hidden: np.ndarray  # (E, N)
    collisions: int
    errors: int

    def repeated(self, times: int) -> Rollouts:
        """The same episodes ``times`` over, one after the other (counts included)."""
        arrays = (self.arc_m, self.speed_mps, self.spacing_m, self.accel_mps2, self.hidden)
        tiled = (np.concatenate([a] * times) for a in arrays)
        return Rollouts(*tiled, self.collisions * times, self.errors * times)


def rollout(
    core: RingCore, act: ActionFn, horizon: int, seed: int, episodes: range | None = None
) -> Rollouts:
    """Run ``act`` on every episode of the core's bank (or ``episodes``)."""
    eps = list(episodes if episodes is not None else range(len(core.bank)))
    n = core.n
    shape = (len(eps), horizon, n)
    arc, speed, spacing, accel = (np.full(shape, np.nan) for _ in range(4))
    rng = np.random.default_rng(seed)
    collisions = errors = 0
    for i, ep in enumerate(eps):
        obs = core.reset(ep)
        for t in range(horizon):
            v0 = core.speed.copy()
            res = core.step(act(core, obs, rng))
            obs = res.obs
            arc[i, t], speed[i, t], spacing[i, t] = core.arc, core.speed, core.spacing
            accel[i, t] = (core.speed - v0) / core.dt
            if res.collision or res.truncated:
                collisions += res.collision
                errors += bool(res.error)
                break
    return Rollouts(arc, speed, spacing, accel, core.bank.hidden[eps], collisions, errors)

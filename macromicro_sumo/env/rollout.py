"""Rollouts: any action function driving the hidden vehicles of every episode of a core.

One loop for every road: a core (the ring's or a section's) exposes its vehicles' state
as arrays (``speed``, ``spacing``, ``leader``, ``lane``, ``arc``) and each step says which
slots are on the road (``active``); slots off the road stay NaN in the rollout.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

# fn(core, obs (N, d), rng) -> accelerations of the hidden vehicles (K,)
ActionFn = Callable[[Any, np.ndarray, np.random.Generator], np.ndarray]


@dataclass
class Rollouts:
    """Per episode, step (1..H) and slot; NaN where no vehicle is on the road (after an
    episode ended early, or off an open section) and, for spacings, with no leader on it."""

    arc_m: np.ndarray
    speed_mps: np.ndarray
    spacing_m: np.ndarray
    accel_mps2: np.ndarray
    lane: np.ndarray
    hidden: np.ndarray  # (E, N)
    collisions: int
    errors: int


def rollout(
    core: Any, act: ActionFn, horizon: int, seed: int, episodes: range | None = None
) -> Rollouts:
    """Run ``act`` on every episode of the core's bank (or ``episodes``)."""
    eps = list(episodes if episodes is not None else range(len(core.bank)))
    shape = (len(eps), horizon, core.n)
    arc, speed, spacing, accel, lane = (np.full(shape, np.nan) for _ in range(5))
    rng = np.random.default_rng(seed)
    collisions = errors = 0
    for i, ep in enumerate(eps):
        obs = core.reset(ep)
        for t in range(horizon):
            v0 = core.speed.copy()
            res = core.step(act(core, obs, rng))
            obs = res.obs
            on = res.active
            speed[i, t, on] = core.speed[on]
            accel[i, t, on] = (core.speed[on] - v0[on]) / core.dt
            with_leader = on & (core.leader >= 0)
            spacing[i, t, with_leader] = core.spacing[with_leader]
            lane[i, t, on], arc[i, t, on] = core.lane[on], core.arc[on]
            if res.collision or res.truncated:
                collisions += res.collision
                errors += bool(res.error)
                break
    return Rollouts(arc, speed, spacing, accel, lane, core.bank.hidden[eps], collisions, errors)

"""``policy.driver_follow``: each driven row's own Krauss reaction time (tau), carried as a
trailing observation column (``with_tau``), so that the rollouts, PPO's stored
observations and the deployment hand the prior the same driver's tau.

The taus are drawn from the observed drivers' tau quantiles (``evaluation.driver_follow``,
at ``env.driver_speed.QUANTILE_LEVELS``) at uniform levels: per (seed, run, vehicle) a hash
(``driver_tau_levels``, ``DriverTaus``: the demand env and the deployment, so that a
driver has the same tau whatever drives it), or per bank slot a seeded generator
(``slot_tau_levels``: the snapshot episodes). The agent reads the column where it has a
``driver_tau`` buffer (``policy.agent``); without one nothing appends it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS, driver_levels

# The draws' tag in ``driver_levels`` and the generator's stream for bank slots.
TAU_TAG = "driver_tau"
SLOT_STREAM = 223


def taus_at(quantiles: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """The taus [s] at uniform ``levels`` (inverse CDF, linear between the kept quantiles)."""
    return np.interp(levels, QUANTILE_LEVELS, quantiles)


def driver_tau_levels(seed: int, run: int, vehicle_ids: Sequence[str]) -> np.ndarray:
    """Per vehicle a uniform level: a hash of (seed, run, vehicle), so that a driver draws
    the same tau whatever drives it and however often its run is repeated."""
    return driver_levels(seed, run, vehicle_ids, TAU_TAG)


def slot_tau_levels(seed: int, shape: tuple[int, ...]) -> np.ndarray:
    """Uniform levels for a bank's (episode, slot) drivers from a generator seeded by
    ``seed`` (its own stream, apart from the desired-speed factors')."""
    return np.random.default_rng([seed, SLOT_STREAM]).random(shape)


def with_tau(obs: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """``obs`` (..., D) with each row's tau [s] as a trailing column (..., D + 1)."""
    taus = np.broadcast_to(np.asarray(taus, dtype=obs.dtype), obs.shape[:-1])
    return np.concatenate([obs, taus[..., None]], axis=-1)


class DriverTaus:
    """The taus of one run's drivers (``policy.driver_follow``): a hash of (the scenario's
    seed, ``run``, vehicle) on the agent's tau ``quantiles``, the same in the demand env and
    in the deployment; called with vehicle IDs, returns their taus [s]."""

    def __init__(self, quantiles: np.ndarray, sc, run: int) -> None:
        self.quantiles = np.asarray(quantiles, dtype=float)
        self.seed, self.run = int(sc.seed), int(run)
        self._known: dict[str, float] = {}

    def __call__(self, vids: Sequence[str]) -> np.ndarray:
        known = self._known
        new = [v for v in vids if v not in known]
        if new:
            got = taus_at(self.quantiles, driver_tau_levels(self.seed, self.run, new))
            known.update(zip(new, got.tolist(), strict=True))
        return np.fromiter(map(known.__getitem__, vids), float, len(vids))

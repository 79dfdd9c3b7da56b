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

from collections.abc import Mapping, Sequence

import numpy as np

from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS, driver_levels

# The draws' tag in ``driver_levels`` and the generator's stream for bank slots.
TAU_TAG = "driver_tau"
SLOT_STREAM = 223
# How fast a driver's tau rises from the one its state supports when it is handed over to
# the tau it drew (``DriverTaus.handed_over``) [s of tau per s]. At 20 m/s behind a leader
# the Krauss prior's safe speed falls by about b v / (v + b tau), 3 m/s per s of tau at
# its b of 4 m/s^2: 0.5 s/s asks some 1.5 m/s^2 of braking more, half an IDM car's decel.
# Drawn 502, prior alone, all 4 runs: 0.2 / 0.5 / 1.0 s/s gave 82 / 74 / 112 emergency
# brakings against 159 without it, speed RMSE 1.115 / 1.112 / 1.104 against 1.111.
HANDOVER_RATE_S_PER_S = 0.5


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


def supported_taus(obs: np.ndarray, prior: Mapping[str, float]) -> np.ndarray:
    """Per row of raw observations (n, D) the tau [s] at which the Krauss prior's safe
    speed (``policy.prior``'s, at ``prior``'s decel, minGap and length) is the vehicle's
    speed: the longest tau its gap to its leader supports without braking. inf where it
    is slower than 0.1 m/s (any tau)."""
    v, spacing, dv = obs[:, 0], obs[:, 2], obs[:, 3]
    b = prior["decel_mps2"]
    gap = np.maximum(spacing - prior["veh_length_m"] - prior["min_gap_m"], 0.0)
    v_leader = np.maximum(v - dv, 0.0)
    moving = v > 0.1
    # -b t + sqrt((b t)^2 + v_l^2 + 2 b gap) = v  <=>  t = (v_l^2 + 2 b gap - v^2) / (2 v b)
    out = np.full(len(v), np.inf)
    out[moving] = (v_leader[moving] ** 2 + 2.0 * b * gap[moving] - v[moving] ** 2) / (
        2.0 * v[moving] * b
    )
    return out


def with_tau(obs: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """``obs`` (..., D) with each row's tau [s] as a trailing column (..., D + 1)."""
    taus = np.broadcast_to(np.asarray(taus, dtype=obs.dtype), obs.shape[:-1])
    return np.concatenate([obs, taus[..., None]], axis=-1)


class DriverTaus:
    """The taus of one run's drivers (``policy.driver_follow``): a hash of (the scenario's
    seed, ``run``, vehicle) on the agent's tau ``quantiles``, the same in the demand env and
    in the deployment; called with vehicle IDs, returns their taus [s].

    ``prior`` (the Krauss prior's parameters by name, ``policy.prior.prior_buffer``): a
    driver is handed over (``handed_over``) where a call gives the observations and the
    step: its tau starts at the one its first observed state supports (``supported_taus``,
    at least the lowest quantile) where its draw is longer, and rises to the draw at
    ``HANDOVER_RATE_S_PER_S``. Why: a driven vehicle arrives at the section at the gap its
    own model kept; a drawn tau longer than that gap supports made the Krauss prior brake
    to its safe speed within one step. On drawn 502 (prior alone, all 4 runs) 151 of the
    159 emergency brakings were at a driver's first driven step, 99 of them the prior's at
    a median drawn tau of 1.76 s, where the entry gap supported 1.04 s; the truth had 1."""

    def __init__(
        self, quantiles: np.ndarray, sc, run: int, prior: Mapping[str, float] | None = None
    ) -> None:
        self.quantiles = np.asarray(quantiles, dtype=float)
        self.seed, self.run = int(sc.seed), int(run)
        self._known: dict[str, float] = {}
        self.prior = prior
        self.dt_s = float(sc.simulation.step_length_s)
        # vehicle -> its tau at the hand-over, and the step of it
        self._first: dict[str, float] = {}
        self._since: dict[str, int] = {}

    def __call__(
        self, vids: Sequence[str], obs: np.ndarray | None = None, step: int | None = None
    ) -> np.ndarray:
        known = self._known
        new = [v for v in vids if v not in known]
        if new:
            got = taus_at(self.quantiles, driver_tau_levels(self.seed, self.run, new))
            known.update(zip(new, got.tolist(), strict=True))
        taus = np.fromiter(map(known.__getitem__, vids), float, len(vids))
        if self.prior is None or obs is None or step is None:
            return taus
        return self.handed_over(vids, taus, obs, step)

    def handed_over(
        self, vids: Sequence[str], taus: np.ndarray, obs: np.ndarray, step: int
    ) -> np.ndarray:
        """``taus`` (the draws of ``vids``) as the hand-over holds them at ``step``, from
        each driver's state at the first step it was asked with observations (``obs``).
        Per step C-level lookups of each driver's start (``_first``, ``_since``), the rows
        of the new ones alone in Python: the same values as a list per vehicle a step."""
        first_of, since_of = self._first, self._since
        new_ids = set(vids).difference(first_of)
        if new_ids:
            new = [i for i, v in enumerate(vids) if v in new_ids]
            ok = supported_taus(obs[new], self.prior)
            floor = float(self.quantiles[0])
            for i, t in zip(new, ok.tolist(), strict=True):
                first_of[vids[i]] = min(taus[i], max(t, floor))
                since_of[vids[i]] = step
        n = len(vids)
        first = np.fromiter(map(first_of.__getitem__, vids), float, n)
        since = step - np.fromiter(map(since_of.__getitem__, vids), float, n)
        return np.minimum(taus, first + HANDOVER_RATE_S_PER_S * self.dt_s * since)

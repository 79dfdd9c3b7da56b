"""``policy.driver_follow``: each driven row's own Krauss reaction time (tau), carried as a
trailing observation column (``with_tau``), so that the rollouts, PPO's stored
observations and the deployment hand the prior the same driver's tau.

The taus are drawn from the observed drivers' tau quantiles (``evaluation.driver_follow``,
at ``env.driver_speed.QUANTILE_LEVELS``) at uniform levels: per (seed, run, vehicle) a hash
(``driver_tau_levels``, ``DriverTaus``: the demand env and the deployment, so that a
driver has the same tau whatever drives it), or per bank slot a seeded generator
(``slot_tau_levels``: the snapshot episodes). The agent reads the column where it has a
``driver_tau`` buffer (``policy.agent``); without one nothing appends it.

``policy.driver_follow = "by_vtype"``: the buffer is a table (``vtype_table``), and a driver
draws at its level from its own vType's observed drivers' quantiles (its vType read from
the running SUMO), else from the pooled ones; the bank slots draw from the pooled ones.
Why: on drawn 501 a Krauss-form tau drawn from all drivers gave the IDM cars the Krauss
cars' discharge headway (1.77 s at 1125 m, truth 2.24 s; docs/deploy-log.md, "Drawn 501").
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping, Sequence
from itertools import repeat

import numpy as np

from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS, driver_levels
from macromicro_sumo.sumo.simulation import Simulation

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


# ``policy.driver_follow = "by_vtype"``: the agent's ``driver_tau`` buffer is a table, one
# row per vType with its first column the vType's key (``vtype_key``) and the quantiles
# after it; its first row, keyed ``POOLED_KEY``, the pooled quantiles ("drawn"'s), which the
# snapshot episodes' slots and a driver of a vType without a row draw from. Keys, not names:
# a float buffer holds them exactly (24 bits fit float32's mantissa), so the checkpoint and
# its loading stay as they are.
POOLED_KEY = -1.0


def vtype_key(vtype: str) -> float:
    """A vType's row key in a ``by_vtype`` table: the low 24 bits of its name's CRC-32."""
    return float(zlib.crc32(vtype.encode()) & 0xFFFFFF)


def vtype_table(pooled: Sequence[float], by_vtype: Mapping[str, Sequence[float]]) -> np.ndarray:
    """The ``by_vtype`` table (1 + n types, 1 + levels) of the ``pooled`` quantiles and each
    vType's (``by_vtype``, in name order); refuses two names with one key."""
    names = sorted(by_vtype)
    keys = [vtype_key(n) for n in names]
    if len(set(keys)) < len(keys):
        raise ValueError(f"vTypes {names}: two share a tau table key; rename one")
    rows = [[POOLED_KEY, *pooled]] + [[k, *by_vtype[n]] for k, n in zip(keys, names, strict=True)]
    return np.asarray(rows, dtype=float)


def pooled_quantiles(quantiles: np.ndarray) -> np.ndarray:
    """The pooled tau quantiles of an agent's ``driver_tau`` buffer: itself (``drawn``), or
    a ``by_vtype`` table's first row."""
    q = np.asarray(quantiles, dtype=float)
    return q if q.ndim == 1 else q[0, 1:]


def sumo_vtypes(vids: Sequence[str]) -> list[str]:
    """The running SUMO's vType of each vehicle (``Simulation.vehicle_type``; the deployment
    and the demand env drive one SUMO)."""
    return list(map(Simulation.vehicle_type, vids))


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
        self,
        quantiles: np.ndarray,
        sc,
        run: int,
        prior: Mapping[str, float] | None = None,
        vtypes_of: Callable[[Sequence[str]], list[str]] = sumo_vtypes,
    ) -> None:
        q = np.asarray(quantiles, dtype=float)
        self.quantiles = pooled_quantiles(q)
        # policy.driver_follow = "by_vtype": a new driver draws, at its level, from its
        # vType's row (``vtypes_of``: the running SUMO's types), else the pooled one.
        self.rows = None if q.ndim == 1 else {float(r[0]): r[1:] for r in q[1:]}
        self.vtypes_of = vtypes_of
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
        known, n = self._known, len(vids)
        # C-level lookups, NaN where a driver is new (no draw is NaN): no set or list of
        # the step's vehicles is built in Python once every driver is known.
        taus = np.fromiter(map(known.get, vids, repeat(np.nan)), float, n)
        miss = np.flatnonzero(np.isnan(taus))
        if len(miss):
            new = [vids[i] for i in miss]
            levels = driver_tau_levels(self.seed, self.run, new)
            if self.rows is None:
                got = taus_at(self.quantiles, levels)
            else:
                rows = [self.rows.get(vtype_key(t), self.quantiles) for t in self.vtypes_of(new)]
                got = np.array(
                    [np.interp(x, QUANTILE_LEVELS, r) for x, r in zip(levels, rows, strict=True)]
                )
            known.update(zip(new, got.tolist(), strict=True))
            taus = np.fromiter(map(known.__getitem__, vids), float, n)
        if self.prior is None or obs is None or step is None:
            return taus
        return self.handed_over(vids, taus, obs, step)

    def handed_over(
        self, vids: Sequence[str], taus: np.ndarray, obs: np.ndarray, step: int
    ) -> np.ndarray:
        """``taus`` (the draws of ``vids``) as the hand-over holds them at ``step``, from
        each driver's state at the first step it was asked with observations (``obs``).
        Per step C-level lookups of each driver's start (``_first``, ``_since``; NaN where
        it is new), the rows of the new ones alone in Python: the same values as a list per
        vehicle a step, and no set of the step's vehicles (~30 us a step at Bremen's)."""
        first_of, since_of, n = self._first, self._since, len(vids)
        first = np.fromiter(map(first_of.get, vids, repeat(np.nan)), float, n)
        new = np.flatnonzero(np.isnan(first))  # no start is NaN (min with a draw)
        if len(new):
            ok = supported_taus(obs[new], self.prior)
            floor = float(self.quantiles[0])
            for i, t in zip(new.tolist(), ok.tolist(), strict=True):
                first_of[vids[i]] = min(taus[i], max(t, floor))
                since_of[vids[i]] = step
            first = np.fromiter(map(first_of.__getitem__, vids), float, n)
        since = step - np.fromiter(map(since_of.__getitem__, vids), float, n)
        return np.minimum(taus, first + HANDOVER_RATE_S_PER_S * self.dt_s * since)

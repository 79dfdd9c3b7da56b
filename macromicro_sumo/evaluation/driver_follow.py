"""Per-driver following: each observed driver's own reaction time (the Krauss-form prior's
tau) from its following pairs, their distribution, and seeded draws of it for the drivers
the data do not show.

Why: the Krauss prior fitted to the pooled pairs has one tau, the shortest followers'. On
the pooled pairs the safe speed binds only on the drivers who follow at about that tau;
the others' pairs fall to the free term, which at a relaxation of 10 s costs them nothing.
Drawn net 502's truth mixes 57% Krauss cars (tau 1 s) with 38% IDM cars (T 1.2 s,
accel 1.5): the pooled fit gave tau 1.056 s and a deployed stream 0.9 m/s faster than the
truth (docs/deploy-log.md, "Drawn 502's +1.0 m/s"). Fitted per driver with the pooled fit's
other parameters (``driver_taus``), its 197 observed drivers with a binding safe speed
give two groups, the Krauss cars at a median 1.065 s (132 of them) and the IDM cars at
1.46 s (57): the IDM's gap at its own T is larger than Gipps' at that tau.

``driver_taus`` is a grid search, not a local fit: a driver's cost in tau is flat where
the safe speed binds on none of its pairs, and a local fit stayed at its start there.
A driver's tau is kept where the safe speed binds on at least ``MIN_BINDING_PAIRS`` of its
pairs at that tau (a driver who always kept a long gap says only that its tau is short
enough) and it is not at the grid's edge (SUMO's game/ramp, a congested merge: 5% of its
Krauss drivers at 0.3 s, the grid's lower end). ``tau_quantiles`` keeps the distribution at ``env.driver_speed.QUANTILE_LEVELS``
where at least ``MIN_DRIVER_TAUS`` drivers give one; ``taus_at`` draws from it at uniform
levels: per (seed, run, vehicle) a hash (``driver_tau_levels``, as a deployed driver's
desired-speed factor), or per bank slot a seeded generator (``slot_tau_levels``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable, Mapping, Sequence
from typing import Any

import numpy as np

from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS
from macromicro_sumo.env.driver_tau import DriverTaus, pooled_quantiles, supported_taus
from macromicro_sumo.env.observed_drivers import FREE_GAP_M, FREE_HEADWAY_S, observed_drivers
from macromicro_sumo.evaluation.krauss_fit import (
    ROBUST_SCALE_MPS2,
    KraussParams,
    behind_leader,
    krauss_policy_accel,
)
from macromicro_sumo.evaluation.micro_data import OutOfSample, keyed_micro_pairs
from macromicro_sumo.policy.prior import prior_buffer

# The taus searched [s]: the Krauss fit's range cut to what a driver on a road keeps.
TAU_GRID_S = np.round(np.arange(0.3, 3.0 + 1e-9, 0.005), 3)
# A driver's tau needs its safe speed binding on this many of its pairs (5 s at 0.5 s
# steps); fewer: the driver is left out (its tau is at most the grid's smallest binding).
MIN_BINDING_PAIRS = 10
# A pair follows where its leader is nearer than FREE_HEADWAY_S x v + FREE_GAP_M (the free
# test of ``env.driver_speed``) and the driver moves (v above this).
MIN_SPEED_MPS = 1.0
# Drivers with a tau needed for a distribution (its median to about +-0.02 s at 502's
# spread); fewer: ``tau_quantiles`` gives None (the prior's one tau stays).
MIN_DRIVER_TAUS = 30
# A vType's own quantiles (``policy.driver_follow = "by_vtype"``) need this many of its
# drivers with a tau; fewer: its drivers draw from the pooled ones. Fewer than the pooled
# distribution's 30: 501's 8% trucks at 10% penetration are a few dozen observed drivers.
MIN_VTYPE_TAUS = 10
# ``driver_gap_taus``: a following pair is steady where the driver neither brakes nor
# speeds up much and keeps its leader's pace above a crawl; a driver's kept tau needs
# this many steady pairs (5 s at 0.5 s steps).
STEADY_ACCEL_MPS2 = 0.3
STEADY_DV_MPS = 1.0
STEADY_MIN_SPEED_MPS = 5.0
MIN_STEADY_PAIRS = 10


def following(obs: np.ndarray) -> np.ndarray:
    """(N,) bool: the pairs whose leader is near (the leader column, the spacing or a gap
    layout's gap, below ``FREE_HEADWAY_S`` x v + ``FREE_GAP_M``) with v above
    ``MIN_SPEED_MPS``."""
    v, spacing = obs[:, 0], obs[:, 2]
    return (v > MIN_SPEED_MPS) & (spacing < v * FREE_HEADWAY_S + FREE_GAP_M)


def _soft_l1(resid: np.ndarray) -> np.ndarray:
    """The Krauss fit's robust loss (``least_squares``' soft L1 at ``ROBUST_SCALE_MPS2``)."""
    z = (resid / ROBUST_SCALE_MPS2) ** 2
    return 2.0 * (np.sqrt(1.0 + z) - 1.0)


def driver_taus(
    obs: np.ndarray,
    accel: np.ndarray,
    keys: Sequence[Hashable],
    params: KraussParams,
    veh_length_m: float,
    dt_s: float,
) -> dict[Hashable, float]:
    """Per driver (``keys``, one per pair) its tau [s]: the ``TAU_GRID_S`` value whose
    Krauss-form accelerations (the other parameters at ``params``) fit its following pairs
    (``following``) best under the robust loss, where the safe speed binds on at least
    ``MIN_BINDING_PAIRS`` of them there and it is inside the grid; the other drivers are
    left out."""
    index: dict[Hashable, int] = {}
    driver = np.fromiter((index.setdefault(k, len(index)) for k in keys), np.int64, len(keys))
    near = following(obs)
    obs, accel, driver = obs[near], accel[near], driver[near]
    if not len(accel):
        return {}
    v, limit = obs[:, 0], obs[:, 1]
    desired = np.maximum(params.speed_factor * limit, 0.1)
    free = np.minimum(params.accel_mps2, (desired - v) / max(params.relax_s, dt_s))
    out: dict[Hashable, float] = {}
    for key, d in index.items():
        m = driver == d
        if not m.any():
            continue
        o, a, f = obs[m], accel[m], free[m]
        # (taus, pairs): every grid tau at once.
        fitted = behind_leader(
            o[None, :, :],
            f[None, :],
            params.decel_mps2,
            TAU_GRID_S[:, None],
            params.min_gap_m,
            veh_length_m,
            dt_s,
        )
        best = int(np.argmin(_soft_l1(fitted - a[None, :]).sum(axis=1)))
        inside = 0 < best < len(TAU_GRID_S) - 1  # at the grid's edge: not identified
        if inside and np.count_nonzero(fitted[best] < f - 1e-9) >= MIN_BINDING_PAIRS:
            out[key] = float(TAU_GRID_S[best])
    return out


def driver_gap_taus(
    obs: np.ndarray,
    accel: np.ndarray,
    keys: Sequence[Hashable],
    params: KraussParams,
    veh_length_m: float,
) -> dict[Hashable, float]:
    """Per driver (``keys``, one per pair) the tau [s] it keeps: the median over its steady
    following pairs (``following``, ``STEADY_*``; at least ``MIN_STEADY_PAIRS``) of the tau
    at which the Krauss form's safe speed is its speed (``env.driver_tau.supported_taus``;
    at pace, gap = v tau). Why: ``driver_taus`` fits the pairs where the safe speed brakes,
    where 501's IDM cars (T 1.2 s) fit the Krauss cars' tau (medians 1.13 / 1.10 s), while
    they keep gaps of about 2.0 s headway to the Krauss cars' 1.5 at 12-22 m/s: the
    IDM's s0 + v T / sqrt(1 - (v / v0)^4), which no braking shows."""
    steady = (
        following(obs)
        & (obs[:, 0] > STEADY_MIN_SPEED_MPS)
        & (np.abs(accel) < STEADY_ACCEL_MPS2)
        & (np.abs(obs[:, 3]) < STEADY_DV_MPS)
    )
    prior = {
        "decel_mps2": params.decel_mps2,
        "veh_length_m": veh_length_m,
        "min_gap_m": params.min_gap_m,
    }
    taus = supported_taus(obs[steady], prior)
    by: dict[Hashable, list[float]] = {}
    for k, t in zip((k for k, m in zip(keys, steady, strict=True) if m), taus, strict=True):
        by.setdefault(k, []).append(float(t))
    return {k: float(np.median(t)) for k, t in by.items() if len(t) >= MIN_STEADY_PAIRS}


def tau_quantiles(taus: Sequence[float]) -> np.ndarray | None:
    """``QUANTILE_LEVELS`` quantiles of the drivers' taus; None with fewer than
    ``MIN_DRIVER_TAUS`` of them (the data do not give a distribution)."""
    if len(taus) < MIN_DRIVER_TAUS:
        return None
    return np.quantile(np.asarray(taus, dtype=float), QUANTILE_LEVELS)


def krauss_accel_per_driver(
    obs: np.ndarray, params: KraussParams, tau_s: np.ndarray, veh_length_m: float, dt_s: float
) -> np.ndarray:
    """``krauss_policy_accel`` with each row's own tau [s] (``tau_s``, one per row)."""
    per_row = dataclasses.replace(params, tau_s=np.asarray(tau_s, dtype=float))
    return krauss_policy_accel(obs, per_row, veh_length_m, dt_s)


def driver_tau_record(
    obs: np.ndarray,
    accel: np.ndarray,
    keys: Sequence[Hashable],
    params: KraussParams,
    veh_length_m: float,
    dt_s: float,
) -> dict[str, object]:
    """What a policy manifest records of the observed drivers' own taus (``driver_taus``
    with the fitted prior's other parameters): how many drivers give one, their 5/25/50/
    75/95% quantiles [s], and the share of them at or below the prior's one tau (502: the
    pooled fit's 1.056 s has 27% of its 216 drivers at or below it; their upper quartile,
    its IDM cars, follows at 1.37 s and beyond), and every quantile (``levels_s``): the
    agent's ``driver_tau`` buffer with ``policy.driver_follow``."""
    return tau_record(driver_taus(obs, accel, keys, params, veh_length_m, dt_s), params)


def driver_vtypes(truth, keys: Sequence[tuple[int, str]]) -> dict[tuple[int, str], str]:
    """The vType (``trajectories.csv``'s ``vtype``) of each (run, vehicle) in ``keys``."""
    traj = truth.trajectories
    if "vtype" not in traj:
        return {}
    first = traj.drop_duplicates(["run", "vehicle_id"])
    of = {
        (int(r), str(v)): str(t)
        for r, v, t in zip(first["run"], first["vehicle_id"], first["vtype"], strict=True)
    }
    return {k: of[k] for k in keys if k in of}


def vtype_levels(
    own: Mapping[Hashable, float], vtypes: Mapping[Hashable, str]
) -> dict[str, dict[str, object]]:
    """Per vType with at least ``MIN_VTYPE_TAUS`` drivers with a tau (``own``; each
    driver's vType in ``vtypes``): how many and its quantiles at ``QUANTILE_LEVELS``
    (``levels_s``), what ``policy.driver_follow = "by_vtype"`` draws a driver of it from."""
    by: dict[str, list[float]] = {}
    for k, t in own.items():
        if k in vtypes:
            by.setdefault(vtypes[k], []).append(t)
    return {
        name: {
            "drivers": len(taus),
            "median_s": round(float(np.median(taus)), 3),
            "levels_s": [float(x) for x in np.quantile(np.asarray(taus), QUANTILE_LEVELS)],
        }
        for name, taus in sorted(by.items())
        if len(taus) >= MIN_VTYPE_TAUS
    }


def tau_record(
    own: Mapping[Hashable, float],
    params: KraussParams,
    vtypes: Mapping[Hashable, str] | None = None,
) -> dict[str, object]:
    """``driver_tau_record`` of the drivers' own taus ``own`` (``driver_taus``); with
    ``vtypes`` (each driver's vType, ``policy.driver_follow = "by_vtype"``) each vType's
    quantiles too (``by_vtype``, ``vtype_levels``)."""
    taus = np.array(list(own.values()), dtype=float)
    q = tau_quantiles(taus)
    extra = {} if vtypes is None else {"by_vtype": vtype_levels(own, vtypes)}
    return {
        "drivers": len(taus),
        "quantiles_s": None
        if q is None
        else {
            f"{level:g}": round(float(np.interp(level, QUANTILE_LEVELS, q)), 3)
            for level in (0.05, 0.25, 0.5, 0.75, 0.95)
        },
        "share_at_or_below_prior": round(float(np.mean(taus <= params.tau_s + 1e-9)), 3)
        if len(taus)
        else None,
        # Every quantile (``QUANTILE_LEVELS``): what policy.driver_follow draws from.
        "levels_s": None if q is None else [float(x) for x in q],
        **extra,
    }


def pair_taus(
    sc,
    keys: Sequence[tuple[int, str]],
    own: Mapping[Hashable, float],
    quantiles: Sequence[float] | None,
) -> np.ndarray | None:
    """Each likelihood pair's driver's tau [s] (``keys``: (run, vehicle ID) per pair,
    ``evaluation.micro_data.keyed_micro_pairs``): its own fitted one (``own``,
    ``driver_taus``) where it has one, else the tau the deployment and the demand env draw
    for that driver (``env.driver_tau.DriverTaus`` on ``quantiles`` as the agent's float32
    buffer holds them); None without quantiles (under ``MIN_DRIVER_TAUS`` drivers: the
    prior's one tau). Why: with the prior's one tau on every pair the residual's likelihood
    fitted the observed drivers as if they shared it, the long-tau drivers' larger gaps
    then a correction the actor, blind to the tau column, applied to every driver."""
    if quantiles is None:
        return None
    # by_vtype's table: the pooled row (no SUMO runs here to give a vType).
    q = pooled_quantiles(np.asarray(quantiles, dtype=np.float32).astype(float))
    out = np.array([own.get(k, np.nan) for k in keys], dtype=float)
    draws: dict[int, DriverTaus] = {}
    for i in np.flatnonzero(np.isnan(out)):
        run, vid = keys[i]
        out[i] = draws.setdefault(run, DriverTaus(q, sc, run))([vid])[0]
    return out


def held_out_pairs(
    sc, truth, runs, agents: Mapping[str, Any], veh_length_m: float
) -> tuple[
    np.ndarray, np.ndarray, dict[str, np.ndarray | None], OutOfSample | None, dict[str, Any]
]:
    """The held-out observed pairs of ``runs`` (``micro_pairs``) for micro consistency,
    with ``held_out_taus`` of their drivers (in-sample), ``out_of_sample_taus`` and their
    record (each agent's ``out_of_sample`` entry beside its in-sample counts)."""
    obs, acc, keys = keyed_micro_pairs(sc, truth, runs)
    taus, record = held_out_taus(sc, truth, runs, keys, agents, veh_length_m)
    later = out_of_sample_taus(sc, obs, acc, keys, agents, veh_length_m)
    if later is not None:
        for name, t in later.taus.items():
            own = later.own[name]
            record[name]["out_of_sample"] = {"pairs": len(t), "own_tau": int(np.sum(own))}
    return obs, acc, taus, later, record


def record_halves(keys: Sequence[Hashable]) -> np.ndarray:
    """(N,) bool: the pairs in the second half of their driver's record (``keys``, one per
    pair, each driver's pairs in the order they were recorded, as ``keyed_micro_pairs``
    gives them): a driver's first n // 2 pairs are its first half, the others its second."""
    count: dict[Hashable, int] = {}
    for k in keys:
        count[k] = count.get(k, 0) + 1
    seen: dict[Hashable, int] = {}
    later = np.empty(len(keys), dtype=bool)
    for i, k in enumerate(keys):
        j = seen.get(k, 0)
        seen[k] = j + 1
        later[i] = j >= count[k] // 2
    return later


def out_of_sample_taus(
    sc,
    obs: np.ndarray,
    accel: np.ndarray,
    keys: Sequence[tuple[int, str]],
    agents: Mapping[str, Any],
    veh_length_m: float,
) -> OutOfSample | None:
    """Each held-out driver's tau fitted on the first half of its pairs (``record_halves``;
    ``driver_taus`` with the agent's prior), for the pairs of the second half, which
    micro consistency scores with it; a driver without a tau from its first half gets the
    deployment's draw (``pair_taus``). For every agent with a ``driver_tau`` buffer and a
    Krauss prior; None where there is none. Why: ``held_out_taus`` fits each driver's tau
    on the same record that is then scored (in-sample): one parameter per driver, chosen
    on the scored pairs."""
    later = record_halves(keys)
    first = ~later
    first_keys = [k for k, f in zip(keys, first, strict=True) if f]
    later_keys = [k for k, f in zip(keys, later, strict=True) if f]
    taus: dict[str, np.ndarray] = {}
    own_of: dict[str, np.ndarray] = {}
    dt = sc.simulation.step_length_s
    for name, agent in agents.items():
        q = getattr(agent, "driver_tau", None)
        if q is None or agent.prior != "krauss":
            continue
        p = prior_buffer(agent)
        params = KraussParams(**{k: p[k] for k in KraussParams.__dataclass_fields__})
        own = driver_taus(obs[first], accel[first], first_keys, params, veh_length_m, dt)
        taus[name] = pair_taus(sc, later_keys, own, q.numpy())
        own_of[name] = np.array([k in own for k in later_keys], dtype=bool)
    return OutOfSample(later, taus, own_of) if taus else None


def held_out_taus(
    sc, truth, runs, keys: Sequence[tuple[int, str]], agents: Mapping[str, Any], veh_length_m: float
) -> tuple[dict[str, np.ndarray | None], dict[str, Any]]:
    """Each held-out pair's driver's tau [s] (``keys``, ``keyed_micro_pairs`` of ``runs``)
    for every agent trained with the drivers' taus (its ``driver_tau`` buffer, a Krauss
    prior): ``pair_taus``, as the training's likelihood pairs take them, with the drivers'
    own taus fitted on ``runs`` (``driver_taus`` with the agent's prior), else the
    deployment's draw; None for the others (the prior's one tau, as before). Returns them
    by agent and what the manifest records (pairs, pairs with the driver's own tau). Why:
    micro consistency scored the held-out drivers with the prior's one tau while the
    training judged every observed driver with its own."""
    taus: dict[str, np.ndarray | None] = {}
    record: dict[str, Any] = {}
    drivers, own_of = None, {}
    for name, agent in agents.items():
        q = getattr(agent, "driver_tau", None)
        if q is None or agent.prior != "krauss":
            taus[name] = None
            continue
        p = prior_buffer(agent)
        params = KraussParams(**{k: p[k] for k in KraussParams.__dataclass_fields__})
        if drivers is None:
            drivers = observed_drivers(sc, truth, runs)
        if params not in own_of:
            dt = sc.simulation.step_length_s
            own_of[params] = driver_taus(
                drivers.obs, drivers.accel, drivers.keys, params, veh_length_m, dt
            )
        own = own_of[params]
        taus[name] = pair_taus(sc, keys, own, q.numpy())
        record[name] = {"pairs": len(keys), "own_tau": sum(k in own for k in keys)}
    return taus, record

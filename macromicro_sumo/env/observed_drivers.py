"""The observed (instrumented) drivers' desired-speed ratios and the Krauss prior's pairs
scaled by them: what ``env.driver_speed`` draws each driven vehicle's factor from.

A vehicle's ratio is the highest v / limit it drove at where it cruised with no leader near
long enough (``observed_drivers``); every other observed vehicle gives a lower bound. Their
distribution under censoring: ``env.driver_speed_ratios``. Split from ``env.driver_speed``
(stop 41) so that the estimate and the per-driver draws are each one module.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from macromicro_sumo.data.section import SectionTruth, recorded_steps, run_section
from macromicro_sumo.env.driver_speed_ratios import (
    ObservedDrivers,
    RatioEstimate,
    ratio_estimate,
)
from macromicro_sumo.env.section_bank import recordable, speed_caps
from macromicro_sumo.env.section_observations import section_observations
from macromicro_sumo.road.leaders import STANDING_MIN_GAP_M, bumper_gap_m
from macromicro_sumo.road.physics import LIMIT_COLUMN, NEXT_LIMIT_COLUMN, observes_gap
from macromicro_sumo.road.section import STOP

# The observation columns that are speed limits (own lane, the look-ahead's next edge).
LIMIT_COLUMNS = (LIMIT_COLUMN, NEXT_LIMIT_COLUMN)
# A sample is free when the leader is at least this many seconds ahead at the own speed
# (plus FREE_GAP_M): Krauss' drivers follow at ~1 s, so at 2 s the leader does not bind
# (its safe speed is above the own: at 40 m/s, 90 m behind a 38 m/s leader, 43 m/s), and
# the vehicle cruises at its own desired speed. At 4 s + 20 m (before) the estimate was
# biased low: fast drivers are rarely that far behind anyone, so the free ones were the
# slow ones (Bremen, every run: 67 vehicles, median 0.971 against SUMO's speedFactor
# median 1.0; at 2 s + 10 m: 227, median 0.985, std 0.104 against 0.1; the largest v /
# limit over each vehicle's whole record: median 0.987).
FREE_HEADWAY_S = 2.0
FREE_GAP_M = 10.0
# ... and when the vehicle is not still accelerating towards it (Krauss accelerates at
# a (1 - sigma U) >= 1.3 m/s^2 at SUMO's defaults; cruising, its dawdling averages ~0).
CRUISE_ACCEL_MPS2 = 1.0
# The free test reads the bumper gap (``road.leaders.bumper_gap_m``: the spacing less the
# leader's length), at least FREE_HEADWAY_S x v + FREE_BUMPER_GAP_M: behind a 5 m car the
# spacing test above (FREE_GAP_M = 5 m + 5 m), behind a 12 m truck 7 m stricter. Why: on the
# signalised arterial 521 cars standing 14.5 m behind a 12 m truck passed the spacing test,
# and their top speeds (0.28-0.54 of the limit) were taken as exact ratios (docs/deploy-log.md,
# "Arterial 521's slow exact ratios"). A leader of unknown length counts as a car.
FREE_BUMPER_GAP_M = 5.0
CAR_LENGTH_M = FREE_GAP_M - FREE_BUMPER_GAP_M
# ... and a sample slower than this share of its limit is not cruising: a car standing at a
# green light before a blocked junction (accel 0, its leader beyond the junction) is not
# at its desired speed (521: three exact ratios of 0.42-0.49 of such cars).
CRUISE_MIN_SHARE = 0.1
# A vehicle's ratio needs this many free cruising samples (5 s at 0.5 s steps): fewer
# leave its maximum below its desired speed (Krauss dawdles below it most steps).
MIN_FREE_SAMPLES = 10
# policy.prior = "krauss" is fitted on ``own_speed_pairs`` where they are at least this many
# (Bremen: 4,500 of 19,000 pairs at 4 s + 20 m), else on every observed pair.
MIN_OWN_PAIRS = 500
# A vehicle whose top speed is within this share of its vehicle's maxSpeed was held there by
# the vehicle (SUMO caps every speed at it), not by its driver: its ratio is a lower bound.
CAP_SHARE = 0.995
# ``unheld``: a Krauss follower this far behind a faster leader (SUMO's default tau, 1 s) may
# go faster than the own speed (its safe speed is above the leader's), so a top speed there
# is the driver's own ...
UNHELD_HEADWAY_S = 1.0
# ... where the leader pulls away, faster by at least this much (the gap grows by 0.25 m a
# step). Why: drawn 522's IDM car main0.117 cruised 2.05 s behind a leader faster by 0.008
# m/s, held there by IDM's interaction term at 0.86 of its true speedFactor (stop 40, hC).
PULL_AWAY_MPS = 0.5
# ... and where its next speed is known and not above the own: a top is a driver's own only
# where the driver does not go faster right after (Krauss at its desired speed keeps it or
# dawdles below it). This much gain is rounding (the CSV's 1e-6 m/s over a 0.5 s step).
# Why: drawn 522's main0.322 had its top at the run's last step, still accelerating at
# 0.78 m/s^2 (under CRUISE_ACCEL_MPS2) at 0.608 x the limit, its true factor 1.100.
UNHELD_ACCEL_MPS2 = 0.01
# ... and not braking harder than Krauss' dawdling (sigma x accel, 0.5 x 2.6 m/s^2 at SUMO's
# defaults): a driver braking harder is held by what the observation does not show. Why:
# drawn 561's IDM car main1.45 braked at 1.94 m/s^2 at 11.8 m/s, 52 m behind a leader 4 m/s
# faster, a top of 0.513 of the limit where its true factor is 0.991.
UNHELD_BRAKE_MPS2 = 1.3
# A lower bound is reached where the vehicle was unheld at a sample within this share of its
# top (``ObservedDrivers.reached``): its top is one sample, Krauss dawdles below its desired
# speed most steps, and on a signalised arterial a car often has its top while it already
# closes on a queue ahead (held there, unheld a few samples before at 0.98-0.99 of it).
# Arterial 521: 40 -> 65 reached bounds, each 0.965-1.0 of its driver's true speedFactor.
REACHED_SHARE = 0.02


def observed_drivers(sc, truth: SectionTruth, runs: np.ndarray) -> ObservedDrivers:
    """``ObservedDrivers`` of ``runs``: a vehicle's ratio is the largest v / limit over its
    record (Krauss' speed never exceeds factor x limit and reaches it between dawdles)
    where it cruised freely for at least ``MIN_FREE_SAMPLES`` samples (it had the road to
    reach it). Over its free cruising samples only (before), ramp vehicles gave 0.44-0.65:
    free on the acceleration lane, waiting to merge, faster only once merged behind a
    leader (Bremen: their largest v / limit 0.86-0.88); a deployed driver drawn at 0.45 is
    a 20 m/s roadblock on a 44 m/s motorway. A vehicle with fewer samples, or whose top
    speed is its vehicle's maxSpeed (``speed_caps``), has its top as a lower bound."""
    dt = sc.simulation.step_length_s
    caps = speed_caps(sc, truth)
    vtype_of: dict[tuple[int, str], str] = {}
    traj = truth.trajectories[truth.trajectories["run"].isin(runs)]
    traj = traj[recordable(sc, traj)] if "observed" in traj else traj.iloc[:0]
    # free cruising samples, max v / limit, max v [m/s]
    best: dict[tuple[int, str], tuple[int, float, float]] = {}
    obs_rows, acc_rows, keys = [], [], []
    full = truth.trajectories[truth.trajectories["run"].isin(runs)]
    # The pairs' leader column as the policy's: the gap where it observes the gap (each
    # leader's vType length; micro_pairs has refused unknown lengths), else the spacing.
    gap = observes_gap(sc.policy.observation)
    vt = truth.vtypes
    length_of = dict(zip(vt["vtype"], vt["length_m"], strict=True)) if "length_m" in vt else {}
    for run, g in full.groupby("run", sort=True):
        section = run_section(truth, int(run))
        watched = set(traj.loc[traj["run"] == run, "vehicle_id"])
        if not watched:
            continue
        for s, speed_next in recorded_steps(g, dt):
            ids = s["vehicle_id"].to_numpy()
            o = np.fromiter((v in watched for v in ids), bool, len(ids))
            if not o.any():
                continue
            lengths = s["vtype"].map(length_of).to_numpy(dtype=float) if length_of else None
            obs, leader, spacing = section_observations(
                section,
                s["lane_index"].to_numpy(),
                s["arc_m"].to_numpy(),
                s["speed_mps"].to_numpy(),
                np.ones(len(s), dtype=bool),
                "lookahead_gap" if gap else "paper",
                length_m=lengths if gap else None,
            )
            obs = obs[:, :4]  # the paper's columns (the gap layout's: the gap in the third)
            v, limit = obs[:, 0], obs[:, 1]
            v1 = np.fromiter((speed_next.get(x, np.nan) for x in ids), float, len(ids))
            accel = (v1 - v) / dt
            bumper = free_gap_m(spacing, leader, lengths, gap)
            cruise = cruising(v, limit, accel, bumper)
            own = unheld(v, limit, accel, bumper, leader)
            types = s["vtype"].to_numpy() if "vtype" in s else np.full(len(s), "")
            for i in np.flatnonzero(o & (limit > 0)):
                key = (int(run), str(ids[i]))
                n, top, vmax, own_top, settled = best.get(key, (0, 0.0, 0.0, 0.0, False))
                r = v[i] / limit[i]
                own_top = max(own_top, r) if own[i] else own_top  # the top where unheld
                # at the (first) top: the next speed known and not above it
                settled = bool(accel[i] <= UNHELD_ACCEL_MPS2) if r > top else settled
                best[key] = (n + int(cruise[i]), max(top, r), max(vmax, v[i]), own_top, settled)
                vtype_of.setdefault(key, str(types[i]))
            pair = o & np.isfinite(accel)
            obs_rows.append(obs[pair])
            acc_rows.append(accel[pair])
            keys += [(int(run), str(x)) for x in ids[pair]]
    ratio, lower, reached, unsettled = {}, {}, set(), set()
    for k, (n, top, vmax, own_top, settled) in best.items():
        capped = vmax >= CAP_SHARE * caps.get(vtype_of[k], np.inf)
        (ratio if n >= MIN_FREE_SAMPLES and not capped else lower)[k] = top
        own = own_top >= (1.0 - REACHED_SHARE) * top > 0.0 and not capped
        if k in lower and own:
            reached.add(k)
        if k in ratio and not settled and not own:
            unsettled.add(k)
    done = frozenset(reached), frozenset(unsettled)
    if not obs_rows:
        return ObservedDrivers(ratio, np.empty((0, 4)), np.empty(0), [], lower, *done)
    obs_all, acc_all = np.concatenate(obs_rows), np.concatenate(acc_rows)
    return ObservedDrivers(ratio, obs_all, acc_all, keys, lower, *done)


def free_gap_m(
    spacing_m: np.ndarray, leader: np.ndarray, length_m: np.ndarray | None, with_length: bool
) -> np.ndarray:
    """The bumper gap the free test reads (``road.leaders.bumper_gap_m``) of a step's
    ``section_observations``' front-to-front ``spacing_m`` and ``leader`` (-1: none, ``STOP``:
    a standing obstacle), with the vehicles' ``length_m`` (None or NaN: ``CAR_LENGTH_M``).
    ``with_length``: the observations were given the lengths (a gap layout), so a standing
    obstacle's spacing is a standing vehicle's of the own length ``STANDING_MIN_GAP_M``
    beyond it; else it is the distance alone, and its gap that distance + that minGap, as
    well. The same gap in either layout."""
    n = len(spacing_m)
    own = (
        np.full(n, CAR_LENGTH_M) if length_m is None else np.nan_to_num(length_m, nan=CAR_LENGTH_M)
    )
    lead_len = np.where(leader >= 0, own[np.maximum(leader, 0)], 0.0)
    lead_len = np.where(leader == STOP, own if with_length else -STANDING_MIN_GAP_M, lead_len)
    return bumper_gap_m(spacing_m, lead_len)


def cruising(v: np.ndarray, limit: np.ndarray, accel: np.ndarray, gap_m: np.ndarray) -> np.ndarray:
    """(N,) bool: the samples at a driver's own desired speed: the bumper gap ``gap_m``
    (``free_gap_m``) at least ``FREE_HEADWAY_S`` x v + ``FREE_BUMPER_GAP_M``, not
    accelerating (below ``CRUISE_ACCEL_MPS2``) and not standing (at least
    ``CRUISE_MIN_SHARE`` of the ``limit``)."""
    free = gap_m >= v * FREE_HEADWAY_S + FREE_BUMPER_GAP_M
    return free & (accel < CRUISE_ACCEL_MPS2) & (v >= CRUISE_MIN_SHARE * limit)


def unheld(
    v: np.ndarray, limit: np.ndarray, accel: np.ndarray, gap_m: np.ndarray, leader: np.ndarray
) -> np.ndarray:
    """(N,) bool: the samples at which nothing but the driver holds the speed (a top speed
    there is its desired one, ``ObservedDrivers.reached``): the next speed known and not
    above the own (``UNHELD_ACCEL_MPS2``) nor braking harder than ``UNHELD_BRAKE_MPS2``, not
    standing (``CRUISE_MIN_SHARE``), and either no
    vehicle ahead within a free bumper gap ``gap_m`` (``cruising``'s; ``leader`` -1 or a
    standing obstacle) or a vehicle leader faster than the own by ``PULL_AWAY_MPS`` at least
    ``UNHELD_HEADWAY_S`` x v + ``FREE_BUMPER_GAP_M`` ahead. Why: on the signalised arterial
    521 most vehicles never cruise freely for ``MIN_FREE_SAMPLES`` samples between the
    lights, but reach their own desired speed there (docs: ``env.driver_speed_ratios``). Not
    a slower vehicle leader, even at a free gap (Bremen: bounds of 0.59 of their driver's
    speedFactor), nor a faster one nearer (521: 0.30 at 4 m/s in a queue 6.8 m behind, 0.60
    and 0.91)."""
    lead_v = np.where(leader >= 0, v[np.maximum(leader, 0)], -np.inf)
    free = (leader < 0) & (gap_m >= v * FREE_HEADWAY_S + FREE_BUMPER_GAP_M)
    pulling_away = (lead_v >= v + PULL_AWAY_MPS) & (
        gap_m >= v * UNHELD_HEADWAY_S + FREE_BUMPER_GAP_M
    )
    own_speed = (accel <= UNHELD_ACCEL_MPS2) & (accel >= -UNHELD_BRAKE_MPS2)
    return (free | pulling_away) & own_speed & (v >= CRUISE_MIN_SHARE * limit)


def free_speed_ratios(sc, truth: SectionTruth, runs: np.ndarray) -> np.ndarray:
    """Per observed vehicle of ``runs`` with at least ``MIN_FREE_SAMPLES`` free cruising
    samples its desired-speed ratio (``observed_drivers``). Sorted; empty where no vehicle
    qualifies."""
    ratios = list(observed_drivers(sc, truth, runs).ratio.values())
    return np.sort(np.asarray(ratios, dtype=float))


def driver_ratios(sc, truth: SectionTruth, runs: np.ndarray) -> RatioEstimate:
    """The observed drivers' ratio distribution over ``runs`` (``ratio_estimate``): the
    quantiles ``policy.driver_speed`` draws from or clips to."""
    return ratio_estimate(observed_drivers(sc, truth, runs), ratio_censoring(sc))


def ratio_censoring(sc) -> str:
    """``policy.driver_ratios`` (``ratio_estimate``'s censoring; a scenario without it:
    "kaplan_meier")."""
    return str(getattr(sc.policy, "driver_ratios", "kaplan_meier"))


def own_speed_pairs(
    drivers: ObservedDrivers, median: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of the vehicles with an exact ratio, their limit columns times their own
    factor (ratio over ``median``, the ratio estimate's; their own median if None): each
    pair as its driver saw the road, so a model fitted to them has one desired speed, the
    median driver's, as a ``"drawn"`` deployment's drivers do. Why (``policy.prior =
    "krauss"``): fitted to every pair, drivers cruising at their own desired speeds, which
    the observation does not carry, looked like drivers that barely accelerate (Bremen:
    free term's relaxation 10 s, its bound).

    With ``policy.driver_ratios = "reached"`` it still takes ``drivers.ratio`` as it is:
    the unsettled exact ratios in, the reached bounds out. Taking the rule's own set
    instead was measured (stop 42, train + val runs) and left: it adds pairs (Bremen
    15,193 -> 15,709, drawn arterial 528 4,540 -> 11,415) but barely moves the fitted
    Krauss prior (speed factor 0.9978 -> 0.9978 and 1.0173 -> 1.0181, tau 1.0815 ->
    1.0818 and 1.1152 -> 1.1079 s, Bremen's accel 1.804 -> 1.846 m/s^2; netgen_corridor
    tau 1.0685 -> 1.0667 s), well inside what a PPO seed moves the deployment by."""
    if not drivers.ratio:
        return drivers.obs[:0], drivers.accel[:0]
    if median is None:
        median = float(np.median(list(drivers.ratio.values())))
    factor = np.array([drivers.ratio.get(k, np.nan) / median for k in drivers.keys])
    keep = np.isfinite(factor)
    return scale_limits(drivers.obs[keep].copy(), factor[keep]), drivers.accel[keep]


def censored_following_pairs(drivers: ObservedDrivers) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of the drivers with a lower bound only (``ObservedDrivers.lower``) where a
    leader is near (the pairs' leader column, the spacing or in a gap layout the bumper gap,
    below ``FREE_HEADWAY_S`` x v + ``FREE_GAP_M``), limits as they are:
    how they follow does not need their desired speed, which they do not show. Why
    (``krauss_pairs``, an open section whose ratios fell back): the exact drivers' own pairs
    alone are a few, selected drivers' (drawn 502: 24 of 235, the free cruisers; 3,712 pairs
    fitted tau 1.02 s, with these 37,282 pairs 1.06 s, its truth's 38% IDM cars at 1.2 s)."""
    if not drivers.lower or not len(drivers.accel):
        return drivers.obs[:0], drivers.accel[:0]
    v, spacing = drivers.obs[:, 0], drivers.obs[:, 2]
    censored = np.fromiter((k in drivers.lower for k in drivers.keys), bool, len(drivers.keys))
    keep = censored & (spacing < v * FREE_HEADWAY_S + FREE_GAP_M)
    return drivers.obs[keep], drivers.accel[keep]


def krauss_pairs(
    sc,
    truth: SectionTruth,
    runs: np.ndarray,
    obs: np.ndarray,
    accel: np.ndarray,
    own_median: bool = False,
    drivers: ObservedDrivers | None = None,
) -> tuple[np.ndarray, np.ndarray, RatioEstimate]:
    """``prior_pairs`` of the Krauss form and the ratio estimate they are scaled by: where it
    fell back to ``DEFAULT_RATIOS``, the prior's speed factor has no data either
    (``evaluation.krauss_fit.fit_krauss``'s ``fixed``), and each pair's limits are scaled by
    its driver's own ratio (over ``DEFAULT_RATIOS``' median, 1): the speed factor held at 1
    then gives each observed driver its own top speed.

    ``own_median``: where the estimate fell back but the speed factor is fitted all the
    same (a closed section, ``pipeline.build.fit_residual_prior``), over the median of the
    pairs' own drivers' ratios instead (``RatioEstimate.pairs_median``), so that the fitted
    speed factor is the typical observed driver's, as a deployed driver's factor (1, or
    drawn around 1) is. Why: scaled over 1, ring_two_lane's pairs (their drivers' median
    0.957) fitted a speed factor relative to limits 4% below the deployed drivers', whose
    prior then cruised towards 12.76 m/s where the observed cars cruise at 11.9
    (docs/deploy-log.md, "ring_two_lane's cruise (stop 31)").

    On an open section whose estimate fell back the censored drivers' following pairs join
    (``censored_following_pairs``); a closed one keeps its own drivers' pairs (stop 31).
    ``drivers``: ``observed_drivers`` of ``runs`` where the caller has them (one pass over
    the trajectories)."""
    if drivers is None:
        drivers = observed_drivers(sc, truth, runs)
    estimate = ratio_estimate(drivers, ratio_censoring(sc))
    if own_median and estimate.fallback and drivers.ratio:
        estimate = dataclasses.replace(
            estimate, pairs_median=float(np.median(list(drivers.ratio.values())))
        )
    own_obs, own_accel = own_speed_pairs(drivers, estimate.pairs_median or estimate.median)
    if estimate.fallback and not truth.section.closed:
        more_obs, more_accel = censored_following_pairs(drivers)
        own_obs = np.concatenate([own_obs, more_obs])
        own_accel = np.concatenate([own_accel, more_accel])
    if len(own_accel) < MIN_OWN_PAIRS:
        return obs, accel, estimate
    return own_obs, own_accel, estimate


def prior_pairs(
    sc, truth: SectionTruth, runs: np.ndarray, obs: np.ndarray, accel: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``policy.prior``'s model is fitted on: for "krauss", ``own_speed_pairs`` of
    ``runs`` where there are at least ``MIN_OWN_PAIRS``; else ``obs``, ``accel`` (every
    observed pair, ``evaluation.micro_data.micro_pairs``)."""
    if sc.policy.prior != "krauss":
        return obs, accel
    return krauss_pairs(sc, truth, runs, obs, accel)[:2]


def scale_limits(obs: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """``obs`` (V, D) with its limit columns times each driver's ``factor`` (V,), in place."""
    for c in LIMIT_COLUMNS:
        if c < obs.shape[1]:
            obs[:, c] *= factor
    return obs

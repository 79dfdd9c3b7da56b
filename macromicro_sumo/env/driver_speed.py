"""Per-driver desired speeds (``policy.driver_speed``): each driven vehicle takes the road's
limits as its own, scaled by a factor drawn once per driver.

Why: one shared policy gives every car one desired speed, where SUMO's drivers each have
their own (``speedFactor``: desired speed = factor x limit, drawn per vehicle from the
vType's distribution, ``normc(1, 0.1, 0.2, 2)`` for passenger cars). On Bremen the truth's
upstream left lanes ran 40-47 m/s where the deployed policy's ran 35-41 (docs/deploy.md,
"Measured"): without fast drivers nobody overtakes on the left.

What is legitimate: a hidden vehicle's own parameters are unknown, but the observed
(instrumented) vehicles' speeds on a free road are data. ``free_speed_ratios`` estimates
each observed vehicle's desired-speed ratio (the highest v / limit it drove at, where it
cruised with no leader near long enough); ``"drawn"`` gives every hidden or deployed driver a ratio drawn from those,
as a factor relative to their median (so the fitted prior's typical cruising speed is
kept and only the spread is added). The factor multiplies the limit columns of the
driver's observation (``scale_limits``): the prior's desired speed is its fitted speed
factor x the driver's own limit, and the residual sees that limit too.

A draw is a hash of (seed, run, vehicle): the same vehicle gets the same factor whatever
method drives and however often a run is repeated (as ``deploy.population.in_share``).

The ratios' distribution under censoring (lower bounds): ``env.driver_speed_ratios``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from macromicro_sumo.data.section import SectionTruth, recorded_steps, run_section, vehicle_level
from macromicro_sumo.env.driver_speed_ratios import (
    QUANTILE_LEVELS,
    ObservedDrivers,
    RatioEstimate,
    ratio_estimate,
)
from macromicro_sumo.env.section_bank import SectionBank, recordable, speed_caps
from macromicro_sumo.env.section_observations import initial_observations, section_observations
from macromicro_sumo.road.leaders import STANDING_MIN_GAP_M, bumper_gap_m
from macromicro_sumo.road.physics import (
    LEADER_COLUMN,
    LIMIT_COLUMN,
    NEXT_LIMIT_COLUMN,
    observes_gap,
)
from macromicro_sumo.road.section import NO_LEADER_GAP_M, STOP

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
# and their top speeds (0.28-0.54 of the limit) were taken as exact ratios (docs/deploy.md,
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
# is the driver's own.
UNHELD_HEADWAY_S = 1.0
# ``"memory"``: a driver first seen slower than this share of the observed drivers' median
# desired speed is queued there (a lane drop's or a red light's queue reaching back to the
# entry), so its speed says nothing of its desired speed: it takes ``"drawn"``'s factor at
# its own level. Before, it kept the slowest observed driver's factor for the whole section:
# on drawn net 522 63% of the deployed drivers entered the queue, and at 0.72 of the median
# led platoons at 16.8 m/s on the one-lane edges where the truth's stream runs 20 (stop 38,
# hD). Not the observed range's lowest ratio: on drawn net 549 cars entering at 25-27 m/s
# behind trucks (0.74-0.81 of its median) are not queued, and drawing them was worse there
# (speed RMSE 4.39 -> 4.90 m/s over 4 runs); 1.6% of its drivers are below 0.65.
# With ``policy.driver_entry = "held"`` a first sight held by what is ahead
# (``held_at_sight``) is drawn as well, whatever its speed.
QUEUED_ENTRY_SHARE = 0.65


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
                n, top, vmax, at_top = best.get(key, (0, 0.0, 0.0, False))
                r = v[i] / limit[i]
                # unheld at its top: at the first sample there, or at a later one as fast
                at_top = bool(own[i]) if r > top else at_top or (r == top and bool(own[i]))
                best[key] = (n + int(cruise[i]), max(top, r), max(vmax, v[i]), at_top)
                vtype_of.setdefault(key, str(types[i]))
            pair = o & np.isfinite(accel)
            obs_rows.append(obs[pair])
            acc_rows.append(accel[pair])
            keys += [(int(run), str(x)) for x in ids[pair]]
    ratio, lower, reached = {}, {}, set()
    for k, (n, top, vmax, at_top) in best.items():
        capped = vmax >= CAP_SHARE * caps.get(vtype_of[k], np.inf)
        (ratio if n >= MIN_FREE_SAMPLES and not capped else lower)[k] = top
        if k in lower and at_top and not capped:
            reached.add(k)
    if not obs_rows:
        return ObservedDrivers(ratio, np.empty((0, 4)), np.empty(0), [], lower, frozenset(reached))
    obs_all, acc_all = np.concatenate(obs_rows), np.concatenate(acc_rows)
    return ObservedDrivers(ratio, obs_all, acc_all, keys, lower, frozenset(reached))


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
    there is its desired one, ``ObservedDrivers.reached``): not accelerating (below
    ``CRUISE_ACCEL_MPS2``; the next speed known), not standing (``CRUISE_MIN_SHARE``), and
    either no vehicle ahead within a free bumper gap ``gap_m`` (``cruising``'s; ``leader``
    -1 or a standing obstacle) or a vehicle leader faster than the own at least
    ``UNHELD_HEADWAY_S`` x v + ``FREE_BUMPER_GAP_M`` ahead. Why: on the signalised arterial 521 most vehicles never
    cruise freely for ``MIN_FREE_SAMPLES`` samples between the lights, but reach their own
    desired speed there (docs: ``env.driver_speed_ratios``). Not a slower vehicle leader,
    even at a free gap (Bremen: bounds of 0.59 of their driver's speedFactor), nor a faster
    one nearer (521: 0.30 at 4 m/s in a queue 6.8 m behind, 0.60 and 0.91)."""
    lead_v = np.where(leader >= 0, v[np.maximum(leader, 0)], -np.inf)
    free = (leader < 0) & (gap_m >= v * FREE_HEADWAY_S + FREE_BUMPER_GAP_M)
    pulling_away = (lead_v > v) & (gap_m >= v * UNHELD_HEADWAY_S + FREE_BUMPER_GAP_M)
    return (free | pulling_away) & (accel < CRUISE_ACCEL_MPS2) & (v >= CRUISE_MIN_SHARE * limit)


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
    free term's relaxation 10 s, its bound)."""
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
    (docs/deploy.md, "ring_two_lane's cruise (stop 31)").

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


def ratio_quantiles(ratios: np.ndarray) -> np.ndarray:
    """``QUANTILE_LEVELS`` of the observed ratios (the agent's ``driver_speed`` buffer); all
    ones where there are none (every driver then the fitted prior's)."""
    if len(ratios) == 0:
        return np.ones(len(QUANTILE_LEVELS))
    return np.quantile(ratios, QUANTILE_LEVELS)


def relative(quantiles: np.ndarray) -> np.ndarray:
    """The quantiles over their median: the factors, so that the fitted prior's speed
    factor stays the median driver's."""
    return quantiles / np.interp(0.5, QUANTILE_LEVELS, quantiles)


def driver_levels(
    seed: int, run: int, vehicle_ids: Sequence[str], tag: str = "driver_speed"
) -> np.ndarray:
    """Per vehicle a uniform level in [0, 1): a hash of (seed, run, vehicle, ``tag``); each
    drawn quantity its own ``tag`` (the desired speed's, ``driver_follow``'s tau's)."""
    return np.array([vehicle_level(seed, run, str(v), tag) for v in vehicle_ids])


def factors_at(quantiles: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """``"drawn"``: the factors at uniform ``levels`` (inverse CDF of ``relative``,
    linear between the kept quantiles)."""
    return np.interp(levels, QUANTILE_LEVELS, relative(quantiles))


def held_at_sight(obs: np.ndarray, gap_layout: bool) -> np.ndarray:
    """(N,) bool: first sights whose speed what is ahead holds, so that it says nothing of
    the driver's desired speed: ``unheld``'s test of one observation (limits unscaled; no
    next speed, so without its acceleration clause): a leader (a vehicle, or a standing
    obstacle: a red light, a lane's end) within ``cruising``'s free bumper gap,
    ``FREE_HEADWAY_S`` x v + ``FREE_BUMPER_GAP_M``, unless it is faster than the own
    (delta v < 0) and at least ``UNHELD_HEADWAY_S`` x v + ``FREE_BUMPER_GAP_M`` ahead. The
    leader column is the bumper gap where ``gap_layout`` (``physics.observes_gap``), else
    the spacing, less ``CAR_LENGTH_M`` (a leader of unknown length counts as a car, as in
    ``free_gap_m``); ``NO_LEADER_GAP_M`` or more: none. The observed drivers' rule
    (``observed_drivers``): a deployed driver's speed counts where an observed one's would."""
    v, lead, dv = obs[:, 0], obs[:, LEADER_COLUMN], obs[:, 3]
    gap = lead if gap_layout else lead - CAR_LENGTH_M
    near = lead < NO_LEADER_GAP_M
    free = ~near | (gap >= v * FREE_HEADWAY_S + FREE_BUMPER_GAP_M)
    pulling_away = (dv < 0) & (gap >= v * UNHELD_HEADWAY_S + FREE_BUMPER_GAP_M)
    return ~(free | pulling_away)


def entry_factors(
    quantiles: np.ndarray,
    speed_mps: np.ndarray,
    limit_mps: np.ndarray,
    levels: np.ndarray | None = None,
    held: np.ndarray | None = None,
) -> np.ndarray:
    """``"memory"``: each driver's speed ratio where it was first seen (its entry, or a
    generated vehicle's start) over the observed median, within the observed drivers'
    range (a car that entered standing still has a desired speed all the same). With
    ``levels`` (uniform, per driver): one first seen below ``QUEUED_ENTRY_SHARE`` of it is
    queued there, and one ``held`` (``held_at_sight``; None: none) is held there by its
    leader: either takes ``"drawn"``'s factor at its level instead. Why the held ones
    (``policy.driver_entry = "held"``): on drawn 522 with ``deploy.merge_reach =
    "occupation"`` the entry queues less deeply, and 9.8% of the drivers, first seen moving
    at 0.65-0.72 of the median in the stream behind their leaders, kept the range's lowest
    ratio (0.717) and led platoons on the one-lane edges (speed RMSE, all 4 runs, 3.422
    -> 2.727 m/s). Not the default: netgen_corridor's 15% first seen within 2 s of a
    leader at about the median are at their own speed (0.460 -> 0.682 m/s drawn)."""
    rel = relative(quantiles)
    ratio = speed_mps / np.maximum(limit_mps, 0.1) / np.interp(0.5, QUANTILE_LEVELS, quantiles)
    kept = np.clip(ratio, rel[0], rel[-1])
    if levels is None:
        return kept
    drawn = ratio < QUEUED_ENTRY_SHARE
    if held is not None:
        drawn |= held
    return np.where(drawn, np.interp(levels, QUANTILE_LEVELS, rel), kept)


def sight_factors(
    quantiles: np.ndarray, obs: np.ndarray, levels: np.ndarray, entry: str, gap_layout: bool
) -> np.ndarray:
    """``"memory"``'s ``entry_factors`` of first-sight observations ``obs`` (V, D), limits
    unscaled, at ``levels``: the queued ones drawn, and with ``entry`` "held"
    (``policy.driver_entry``) the ``held_at_sight`` ones. The one rule of Stage II's banks
    (``with_driver_factors``) and the deployment (``DriverSpeeds``)."""
    held = held_at_sight(obs, gap_layout) if entry == "held" else None
    return entry_factors(quantiles, obs[:, 0], obs[:, LIMIT_COLUMN], levels, held)


def driver_entry(sc) -> str:
    """``policy.driver_entry`` (a scenario without it: "queued")."""
    return str(getattr(sc.policy, "driver_entry", "queued"))


def scale_limits(obs: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """``obs`` (V, D) with its limit columns times each driver's ``factor`` (V,), in place."""
    for c in LIMIT_COLUMNS:
        if c < obs.shape[1]:
            obs[:, c] *= factor
    return obs


def with_driver_factors(
    bank: SectionBank,
    kind: str,
    quantiles: np.ndarray,
    seed: int,
    obs0: np.ndarray,
    entry: str = "queued",
    gap_layout: bool = False,
) -> SectionBank:
    """``bank`` with a factor per episode and hidden slot (``kind`` "drawn": from
    ``quantiles``, seeded; "memory": from its generated start, ``obs0`` the valid slots'
    initial observations, ``env.section_observations.initial_observations``, whose leader
    column is the bumper gap where ``gap_layout``: ``sight_factors`` by ``entry``, a queued
    (or held) start drawn at a seeded level, as a deployed driver is); observed slots keep 1
    (they replay their records; the likelihood's pairs are the recorded ones)."""
    if kind == "memory":
        factor = np.ones(bank.valid.shape)
        levels = np.random.default_rng([seed, 212]).random(bank.valid.shape)[bank.valid]
        factor[bank.valid] = sight_factors(quantiles, obs0, levels, entry, gap_layout)
    else:
        levels = np.random.default_rng([seed, 211]).random(bank.valid.shape)
        factor = factors_at(quantiles, levels)
    return dataclasses.replace(bank, driver_factor=np.where(bank.valid & bank.hidden, factor, 1.0))


def drivers_bank(sc, section, bank: SectionBank, quantiles: np.ndarray, seed: int) -> SectionBank:
    """``bank`` with its hidden drivers' factors (``sc.policy.driver_speed``, not "none"):
    ``with_driver_factors`` fed the generated starts where "memory" reads them."""
    kind = sc.policy.driver_speed
    obs0 = initial_observations(sc, section, bank) if kind == "memory" else np.empty((0, 4))
    gap = kind == "memory" and observes_gap(sc.policy.observation)
    return with_driver_factors(bank, kind, quantiles, seed, obs0, driver_entry(sc), gap)


class DriverSpeeds:
    """A deployment run's (or a demand episode's, ``env.demand``) drivers' factors: each
    vehicle's set when it is first driven (``"drawn"``: by ``driver_levels`` of (seed,
    run, vehicle); ``"memory"``: ``sight_factors`` of its observation then) and kept while
    it is driven."""

    def __init__(self, quantiles: np.ndarray, sc, run: int) -> None:
        self.quantiles = np.asarray(quantiles, dtype=float)
        self.relative = relative(self.quantiles)  # ``factors_at``'s, once a run, not a call
        self.kind, self.seed, self.run = sc.policy.driver_speed, sc.seed, run
        # "memory": ``policy.driver_entry``, and whether the leader column is the gap
        self.entry = driver_entry(sc)
        self.gap = self.kind == "memory" and observes_gap(sc.policy.observation)
        self.factor: dict[str, float] = {}

    def __call__(self, vehicle_ids: list[str], obs: np.ndarray) -> np.ndarray:
        """Per vehicle its factor; ``obs``: their observations now (``policy.observation``'s
        layout), limits unscaled."""
        new = [i for i, v in enumerate(vehicle_ids) if v not in self.factor]
        if new:
            ids = [vehicle_ids[i] for i in new]
            levels = driver_levels(self.seed, self.run, ids)
            if self.kind == "memory":  # a queued or held one as "drawn" (``sight_factors``)
                f = sight_factors(self.quantiles, obs[new], levels, self.entry, self.gap)
            else:
                f = np.interp(levels, QUANTILE_LEVELS, self.relative)  # factors_at's values
            self.factor.update(zip(ids, f.tolist(), strict=True))
        return np.fromiter(map(self.factor.__getitem__, vehicle_ids), float, len(vehicle_ids))

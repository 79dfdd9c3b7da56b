"""Per-driver desired speeds (``policy.driver_speed``): each driven vehicle takes the road's
limits as its own, scaled by a factor drawn once per driver.

Why: one shared policy gives every car one desired speed, where SUMO's drivers each have
their own (``speedFactor``: desired speed = factor x limit, drawn per vehicle from the
vType's distribution, ``normc(1, 0.1, 0.2, 2)`` for passenger cars). On Bremen the truth's
upstream left lanes ran 40-47 m/s where the deployed policy's ran 35-41 (docs/deploy-log.md,
"Measured"): without fast drivers nobody overtakes on the left.

What is legitimate: a hidden vehicle's own parameters are unknown, but the observed
(instrumented) vehicles' speeds on a free road are data. ``env.observed_drivers`` estimates
each observed vehicle's desired-speed ratio (the highest v / limit it drove at, where it
cruised with no leader near long enough); ``"drawn"`` gives every hidden or deployed driver a ratio drawn from those,
as a factor relative to their median (so the fitted prior's typical cruising speed is
kept and only the spread is added). The factor multiplies the limit columns of the
driver's observation (``env.observed_drivers.scale_limits``): the prior's desired speed is its fitted speed
factor x the driver's own limit, and the residual sees that limit too.

A draw is a hash of (seed, run, vehicle): the same vehicle gets the same factor whatever
method drives and however often a run is repeated (as ``deploy.population.in_share``).

The ratios' distribution under censoring (lower bounds): ``env.driver_speed_ratios``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from macromicro_sumo.data.section import split_runs, vehicle_level
from macromicro_sumo.env.driver_speed_ratios import (
    QUANTILE_LEVELS,
    ObservedDrivers,
    quantile_median,
    ratio_estimate,
)
from macromicro_sumo.env.observed_drivers import (
    CAR_LENGTH_M,
    FREE_BUMPER_GAP_M,
    FREE_HEADWAY_S,
    REACHED_SHARE,
    UNHELD_HEADWAY_S,
    observed_drivers,
    ratio_censoring,
)
from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.env.section_observations import initial_observations
from macromicro_sumo.road.physics import LEADER_COLUMN, LIMIT_COLUMN, observes_gap
from macromicro_sumo.road.section import NO_LEADER_GAP_M

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
# ``policy.driver_entry = "auto"`` (``entry_choice``): "held" where the observed drivers' own
# held first sights are below their own speed, "queued" where they are at it. At it: the
# first sight's v / limit within ``REACHED_SHARE`` of the driver's top v / limit over its
# record (the tolerance a top is "reached" with), at the median of the held first sights
# that "queued" keeps (at least ``QUEUED_ENTRY_SHARE`` of the observed median: the two rules
# differ on those alone; a sight standing or crawling in a queue is drawn by both).
# Train + val runs' observed drivers (stop 45), those held sights and their median first
# sight / top: netgen_corridor 7, 1.00 (departSpeed "desired": inserted at the own speed),
# drawn 522 33, 0.88 (departSpeed "max": at the safe speed behind the queue), 549 133,
# 0.93, 501 17, 0.75, 563 11, 0.91; the signalised arterials' held sights stand in a
# red's queue: 528 0 of 62, 521 2 of 61, 837 3 of 140 ("queued"; with every held sight,
# stop 44: "held" at 0.13, 0.22, 0.27); 565's 25 of 62 move at 0.79 of their tops ("held",
# which lost there at stop 45's defaults, 0.773 -> 0.853 m/s). At stop 46's (merge_reach
# "occupation" on lanes that end, command_dawdle "signals"), retrained with "auto", all 4
# runs, policy: 522 3.624 -> 3.023, 501 2.670 -> 2.454, 565 0.748 -> 0.725, 1161 1.061 ->
# 1.037, 1169 2.190 -> 2.057, 615 0.896 -> 0.896, 563 1.011 -> 1.035 (its deployed drivers the
# same under both: Stage II's training);
# netgen and Bremen md5-equal (stop 47, hM47): the default.
ENTRY_AT_OWN_SHARE = 1.0 - REACHED_SHARE
# Fewer observed held first sights than this tell nothing: "queued".
MIN_HELD_SIGHTS = 5
# ``policy.driver_entry = "insertion"`` (``at_insertion``): a net whose demand inserts at
# departSpeed "max" puts a vehicle in at SUMO's safe speed behind a slower leader, Krauss's
# vsafe(gap - minGap, leader speed) at the typical car's decel and tau (SUMO's defaults for
# passenger cars), even where the gap is beyond ``held_at_sight``'s free gap: drawn 522's
# truth (all 4 runs, 351 first sights at the entry moving at 0.65 of the limit or more): 307
# held by the free-gap rule at a median -0.16 m/s from vsafe, and 16 of the 44 unheld ones
# below their top (under 0.95 of it), at -1.7 to +0.7 m/s from vsafe (IDM cars and trucks
# brake less hard: below it). Such a sight is a lower bound on the desired speed.
INSERTION_DECEL_MPS2 = 4.5
INSERTION_TAU_S = 1.0
INSERTION_MIN_GAP_M = 2.5
INSERTION_BELOW_MPS = 1.5  # a sight this far below vsafe or less ...
INSERTION_ABOVE_MPS = 0.5  # ... to this far above it is at the insertion speed


def ratio_quantiles(ratios: np.ndarray) -> np.ndarray:
    """``QUANTILE_LEVELS`` of the observed ratios (the agent's ``driver_speed`` buffer); all
    ones where there are none (every driver then the fitted prior's)."""
    if len(ratios) == 0:
        return np.ones(len(QUANTILE_LEVELS))
    return np.quantile(ratios, QUANTILE_LEVELS)


def relative(quantiles: np.ndarray) -> np.ndarray:
    """The quantiles over their median: the factors, so that the fitted prior's speed
    factor stays the median driver's."""
    return quantiles / quantile_median(quantiles)


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
    (``observed_drivers``): a deployed driver's speed counts where an observed one's would.
    Acceleration does not tell a held sight in a queue from one cruising in a platoon
    (stop 41): a first sight is mostly the vehicle's insertion, SUMO's acceleration 0 there
    (drawn 522 98.6% of them, netgen_corridor 100%), and one step later, in the truths,
    held sights accelerate at 1 m/s^2 or more only where they stood (already queued:
    522 7.7%, netgen and 549 none). 522's held ones brake (median -0.41 m/s^2), at a
    median 0.43 of their true desired speed (inserted at departSpeed "max"); netgen's are
    at theirs (departSpeed "desired": its observed drivers' held first sights at 1.00 of
    their own ratios). Which a net's are, its observed drivers tell (docs, stop 41)."""
    v, lead, dv = obs[:, 0], obs[:, LEADER_COLUMN], obs[:, 3]
    gap = lead if gap_layout else lead - CAR_LENGTH_M
    near = lead < NO_LEADER_GAP_M
    free = ~near | (gap >= v * FREE_HEADWAY_S + FREE_BUMPER_GAP_M)
    pulling_away = (dv < 0) & (gap >= v * UNHELD_HEADWAY_S + FREE_BUMPER_GAP_M)
    return ~(free | pulling_away)


def at_insertion(obs: np.ndarray, gap_layout: bool) -> np.ndarray:
    """(N,) bool: first sights behind a slower leader (a vehicle within ``NO_LEADER_GAP_M``,
    delta v > 0) at the speed SUMO inserts a vehicle at with departSpeed "max": Krauss's
    safe speed vsafe = -b tau + sqrt((b tau)^2 + vL^2 + 2 b (gap - minGap)) at
    ``INSERTION_DECEL_MPS2``, ``INSERTION_TAU_S``, ``INSERTION_MIN_GAP_M``, within
    ``INSERTION_BELOW_MPS`` below to ``INSERTION_ABOVE_MPS`` above it. The gap as
    ``held_at_sight`` reads it (the spacing less ``CAR_LENGTH_M`` where not
    ``gap_layout``)."""
    v, lead, dv = obs[:, 0], obs[:, LEADER_COLUMN], obs[:, 3]
    gap = lead if gap_layout else lead - CAR_LENGTH_M
    v_lead = v - dv
    bt = INSERTION_DECEL_MPS2 * INSERTION_TAU_S
    room = np.maximum(gap - INSERTION_MIN_GAP_M, 0.0)
    vsafe = -bt + np.sqrt(bt**2 + np.maximum(v_lead, 0.0) ** 2 + 2 * INSERTION_DECEL_MPS2 * room)
    near = (lead < NO_LEADER_GAP_M) & (dv > 0)
    return near & (v >= vsafe - INSERTION_BELOW_MPS) & (v <= vsafe + INSERTION_ABOVE_MPS)


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
    ratio = speed_mps / np.maximum(limit_mps, 0.1) / quantile_median(quantiles)
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
    (``policy.driver_entry``) the ``held_at_sight`` ones; "insertion" draws those and the
    ones ``at_insertion`` as well (a lower bound on the desired speed; drawn above their own
    ratio instead lost on drawn 522, 2.377 -> 2.806 m/s, stop 48). The one rule of Stage
    II's banks (``with_driver_factors``) and the deployment (``DriverSpeeds``)."""
    held = None
    if entry in ("held", "insertion"):
        held = held_at_sight(obs, gap_layout)
    if entry == "insertion":
        held |= at_insertion(obs, gap_layout)
    return entry_factors(quantiles, obs[:, 0], obs[:, LIMIT_COLUMN], levels, held)


@dataclasses.dataclass(frozen=True)
class EntryChoice:
    """``entry_choice``'s answer: the rule (``entry``), the observed held first sights it
    read (``held_sights``: those "queued" keeps) and their median first-sight v / limit over
    their top (``at_own``; NaN where none); the same of the free ones (not held, kept:
    ``free_sights``, ``free_at_own``)."""

    entry: str
    held_sights: int
    at_own: float
    free_sights: int = 0
    free_at_own: float = float("nan")


def first_sights(observed: ObservedDrivers) -> np.ndarray:
    """The indices of each observed driver's first pair (its first sight on the section;
    ``observed.keys`` are in time order within a run)."""
    _, first = np.unique(np.array([f"{r}|{v}" for r, v in observed.keys]), return_index=True)
    return np.sort(first)


def entry_choice(
    observed: ObservedDrivers, gap_layout: bool, censoring: str = "kaplan_meier"
) -> EntryChoice:
    """``policy.driver_entry = "auto"``: "held" where the observed drivers' first sights that
    what is ahead holds (``held_at_sight``) and "queued" keeps (v / limit at least
    ``QUEUED_ENTRY_SHARE`` of the median of the ratios, ``ratio_estimate`` under
    ``censoring``, as the drivers' factors read them) are below their drivers' own speed
    (their median first-sight v / limit under ``ENTRY_AT_OWN_SHARE`` of the driver's top v /
    limit over its record, an exact ratio or a lower bound: the share is then an upper
    bound), else "queued". Why: whether a held first sight says the driver's desired speed is
    a property of how the net's demand inserts vehicles, which its observed drivers show:
    netgen_corridor inserts at the own speed (held first sights 1.00 of their tops), so
    drawing them cost 0.460 -> 0.682 m/s; drawn 522 at the safe speed behind the queue,
    where keeping them cost 2.39 -> 3.46 m/s with deploy.merge_reach "occupation" (stop 43).
    Only the sights "queued" keeps: a signalised arterial's held first sights mostly stand
    in a red's queue (528: 62, at a median 0.13 of their tops), which "queued" draws as well,
    so they say nothing of which rule fits; read with them, 528 chose "held" and lost 1.370
    -> 1.465 m/s (stop 44), where it has none of the others (stop 45). A per-sight share of
    the median (below 0.8) changed netgen too (0.460 -> 0.480) and was worse on 522 (2.73
    against held's 2.39; stop 43, hO43).
    "insertion" instead of "held" where the free first sights (neither held nor queued) are
    below their drivers' own speed as well (at least ``MIN_HELD_SIGHTS``, their median under
    ``ENTRY_AT_OWN_SHARE`` of their tops): the net inserts slower than the drivers want even
    beyond the free gap (departSpeed "max" behind slower leaders). Train + val observed
    drivers (stop 47): 522 5 free sights at 0.806; 549, 501, 563, 1045, 1169, 565, 615, 1161,
    netgen all at 1.000 (unchanged: "held" / "queued"). Why not wherever "held": deployed, all
    4 runs, "insertion" wins on 522 (2.377 -> 2.318; policy trained auto 3.023 -> 2.241),
    549 (3.587 -> 3.249), 1169, 615 by 0.01-0.02, but loses on arterial 1161 (1.028 ->
    1.052; stop 48, hM48)."""
    if not observed.keys:
        return EntryChoice("queued", 0, float("nan"))
    idx = first_sights(observed)
    obs = observed.obs[idx]
    held = held_at_sight(obs, gap_layout)
    keys = [observed.keys[i] for i in idx.tolist()]
    top = np.array([observed.ratio.get(k, observed.lower.get(k, np.nan)) for k in keys])
    ratio = obs[:, 0] / np.maximum(obs[:, LIMIT_COLUMN], 0.1)
    median = ratio_estimate(observed, censoring).median
    kept = ratio / median >= QUEUED_ENTRY_SHARE  # ``entry_factors``' test, the other way
    ok = held & kept & np.isfinite(top) & (top > 0)
    n = int(ok.sum())
    at_own = float(np.median(ratio[ok] / top[ok])) if n else float("nan")
    below = _below_own(n, at_own)
    free = ~held & kept & np.isfinite(top) & (top > 0)
    n_free = int(free.sum())
    free_at_own = float(np.median(ratio[free] / top[free])) if n_free else float("nan")
    slow_free = _below_own(n_free, free_at_own)
    entry = ("insertion" if slow_free else "held") if below else "queued"
    return EntryChoice(entry, n, at_own, n_free, free_at_own)


def resolved_entry(sc, truth, runs: np.ndarray | None = None) -> tuple[Any, EntryChoice | None]:
    """``sc`` with ``policy.driver_entry`` "auto" resolved (``entry_choice`` of the observed
    drivers of ``runs``; None: the train + val runs, those the drivers' ratios come from),
    and the choice; ``sc`` itself and None where it is not "auto". Where ``policy.driver_speed`` is
    not "memory" nobody reads the entry: "queued". Every stage that builds drivers (Stage
    II's banks and demand episodes, a prior's deployment, the deployment) resolves it from
    the same runs, so they read one rule; what a stage records keeps "auto". Each read steps
    every recorded scene of the runs: a stage resolves once where it loads the truth and
    passes the resolved scenario down (the evaluation to each agent's bank)."""
    if getattr(sc.policy, "driver_entry", "queued") != "auto":
        return sc, None
    if sc.policy.driver_speed != "memory":
        choice = EntryChoice("queued", 0, float("nan"))
    else:
        if runs is None:
            splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
            runs = np.concatenate([splits["train"], splits["val"]])
        drivers = observed_drivers(sc, truth, runs)
        choice = entry_choice(drivers, observes_gap(sc.policy.observation), ratio_censoring(sc))
    policy = dataclasses.replace(sc.policy, driver_entry=choice.entry)
    return dataclasses.replace(sc, policy=policy), choice


def _below_own(sights: int, at_own: float) -> bool:
    """``entry_choice``'s test of a kind of first sight: at least ``MIN_HELD_SIGHTS`` of them,
    their median share of their drivers' tops under ``ENTRY_AT_OWN_SHARE``."""
    return sights >= MIN_HELD_SIGHTS and at_own < ENTRY_AT_OWN_SHARE


def entry_record(choice: EntryChoice) -> dict[str, Any]:
    """What a stage records of ``policy.driver_entry = "auto"`` resolved (``entry_choice``):
    the rule, the observed first sights it read and why, so that a manifest says which rule
    its policy trained with (auto's meaning moved at stop 48: "insertion" where the free
    sights are slow too). NaN shares (no such sight) are None, which JSON can hold."""

    def share(x: float) -> float | None:
        return round(float(x), 4) if np.isfinite(x) else None

    # Why, by the rule entry_choice resolved (its test, _below_own, is not applied again).
    test = f"at least {MIN_HELD_SIGHTS} sights, median under {ENTRY_AT_OWN_SHARE:g} of their tops"
    if choice.entry == "insertion":
        why = f"held and free first sights both below their drivers' speed ({test}): insertion"
    elif choice.entry == "held":
        why = f"held first sights below their drivers' speed, free ones not ({test}): held"
    elif choice.held_sights == 0 and choice.free_sights == 0:
        why = "no observed first sight read (none, or policy.driver_speed not memory): queued"
    else:
        why = f"held first sights not below their drivers' speed ({test}): queued"
    return {
        "setting": "auto",
        "resolved": choice.entry,
        "held_sights": int(choice.held_sights),
        "held_at_own": share(choice.at_own),
        "free_sights": int(choice.free_sights),
        "free_at_own": share(choice.free_at_own),
        "why": why,
    }


def driver_entry(sc) -> str:
    """``policy.driver_entry`` (a scenario without it: "queued"); "auto" must have been
    resolved (``entry_choice``) before a "memory" driver reads it. Where
    ``policy.driver_speed`` is not "memory" nobody reads the entry: "queued", as
    ``resolved_entry`` resolves it there (before, "auto" unresolved was refused there too:
    a demand episode's or the warm-up's "drawn" drivers built from the scenario as set)."""
    entry = str(getattr(sc.policy, "driver_entry", "queued"))
    if getattr(sc.policy, "driver_speed", "memory") != "memory":
        return "queued"
    if entry == "auto":
        raise ValueError(
            f"{getattr(sc, 'source', 'scenario')}: policy.driver_entry 'auto' is resolved from "
            "the observed drivers (env.driver_speed.entry_choice) before the drivers read it"
        )
    return entry


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

    def __call__(self, vehicle_ids: list[str], obs: np.ndarray | None) -> np.ndarray:
        """Per vehicle its factor; ``obs``: their observations now (``policy.observation``'s
        layout), limits unscaled ("drawn" reads none: None will do)."""
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

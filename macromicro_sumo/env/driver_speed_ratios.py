"""The observed drivers' desired-speed ratios as a distribution (``env.driver_speed``'s
estimate, which ``policy.driver_speed`` draws from or clips to).

Censoring (``ratio_estimate``): a vehicle's top v / limit is its desired ratio only where it
cruised freely long enough and was not held at its vehicle's own maxSpeed (``speed_caps``);
elsewhere it is a lower bound (a queue follower, a truck at its governor). The ratios are a
Kaplan-Meier estimate over both; with fewer than ``MIN_EXACT_RATIOS`` exact ones the data do
not identify them and SUMO's default speedFactor distribution is kept (``DEFAULT_RATIOS``):
on SUMO's congested ``game/ramp`` 23 of 249 observed vehicles cruised freely, their median
0.83 (trucks at 27.78 / 33.33 m/s among them) where SUMO's speedFactor median is 1.0.

``policy.driver_ratios = "reached"``: a lower bound whose top speed the vehicle reached with
nothing holding it there (``ObservedDrivers.reached``, ``env.observed_drivers.unheld``) counts as
exact. Why: on the signalised arterial 521, 212 of 261 observed vehicles give a bound, and
the bounds above 0.8 are 0.98-0.99 of their driver's true speedFactor (re-read from SUMO,
the median over each tenth of the bounds). Kaplan-Meier gave their weight to the few fast
exact ratios above them: its median 1.12 where the observed drivers' true one is 1.00
(reached: 40 bounds, 0.965-1.0 of their true factor; the median 1.03). On netgen_corridor
no bound qualifies; on Bremen 10 of 58 (0.995-1.0; the median 1.015 -> 1.007, true 1.008).
Stop 41: a top is reached where the driver was unheld at a sample within
``env.observed_drivers.REACHED_SHARE`` of it, its next speed not above the own, a leader
pulling away only where faster by ``PULL_AWAY_MPS`` (drawn 522's IDM misfires at 0.55 and
0.84 of the true factor are gone), and an exact ratio whose top had no next speed or was
still rising is a bound (``ObservedDrivers.unsettled``). Medians against the observed
drivers' true one (train + val runs; kaplan_meier / reached / true): 521 1.119 / 1.017 /
0.998, 528 1.140 / 1.027 / 1.012, 549 0.966 / 0.995 / 0.995, 522 1.016 / 1.009 / 1.008,
Bremen 1.015 / 1.005 / 1.008, drawn 501 1.028 / 1.003 / 1.003; not tuned for: arterial 537
1.038 / 1.002 / 0.998, drawn 566 1.016 / 0.994 / 0.993 (12 nets, reached within 0.02 on
each, kaplan_meier on 6).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.stats import truncnorm

# Quantile levels at which a fitted ratio distribution is kept (the agent's buffer).
QUANTILE_LEVELS = np.linspace(0.0, 1.0, 41)
# Exact (uncensored) ratios needed to estimate the distribution (its median to +-0.02 at
# SUMO's spread of 0.1); fewer: ``DEFAULT_RATIOS``. Measured: netgen_corridor 37,
# game/ramp 23 (congested, the free ones the slow), Bremen and the drawn nets 97-227.
MIN_EXACT_RATIOS = 30
# Exact ratios this many interquartile ranges below the lower quartile count as lower
# bounds (``ratio_estimate``; Tukey's far-out fence).
OUTLIER_IQR = 3.0
# SUMO's default speedFactor distribution (normc(1, 0.1), here cut at two deviations as
# ``deploy.population.SwitchedType`` draws it) at ``QUANTILE_LEVELS``.
DEFAULT_RATIOS = truncnorm.ppf(QUANTILE_LEVELS, -2.0, 2.0, loc=1.0, scale=0.1)


@dataclasses.dataclass(frozen=True)
class ObservedDrivers:
    """The observed vehicles of some runs: each one's desired-speed ratio where it cruised
    freely long enough (``ratio``, keyed by (run, vehicle id)), and their (observation,
    acceleration) pairs ("paper" observations: [v, limit, spacing, delta_v]) with the
    (run, vehicle id) of each."""

    ratio: dict[tuple[int, str], float]
    obs: np.ndarray
    accel: np.ndarray
    keys: list[tuple[int, str]]
    # Lower bounds: the top v / limit of every other observed vehicle (too few free cruising
    # samples, or held at its vehicle's maxSpeed).
    lower: dict[tuple[int, str], float] = dataclasses.field(default_factory=dict)
    # The keys of ``lower`` whose top the vehicle reached with nothing holding it there (not
    # accelerating, nor standing, with a free gap or a leader at least as fast; not its
    # vehicle's maxSpeed): their bound is their ratio (``ratio_estimate``'s "reached").
    reached: frozenset[tuple[int, str]] = frozenset()
    # The keys of ``ratio`` whose top had no next speed or was still accelerating (the
    # vehicle left the section, or the run ended, on its way up) and was not reached: a lower
    # bound in ``ratio_estimate``'s "reached" (drawn 549: 36 exact ratios at their last row,
    # 0.88 / 0.93 of their Krauss / IDM car's true factor).
    unsettled: frozenset[tuple[int, str]] = frozenset()


@dataclasses.dataclass(frozen=True)
class RatioEstimate:
    """The drivers' desired-speed ratios: ``QUANTILE_LEVELS`` quantiles, the exact and
    censored counts they come from, and why the data did not identify them (then
    ``DEFAULT_RATIOS``), or "" where they did."""

    quantiles: np.ndarray
    exact: int
    lower_bounds: int
    fallback: str = ""
    # The median the Krauss prior's pairs are scaled over where it is not ``median``
    # (``krauss_pairs``' own_median); None: ``median``.
    pairs_median: float | None = None
    # Lower bounds taken as exact (``ratio_estimate``'s "reached"; counted in ``exact``).
    reached: int = 0

    @property
    def median(self) -> float:
        return quantile_median(self.quantiles)

    def record(self) -> dict[str, object]:
        """What a policy manifest records of it."""
        out: dict[str, object] = {
            "exact": self.exact,
            "lower_bounds": self.lower_bounds,
            "median": round(self.median, 4),
            "fallback": self.fallback,
        }
        if self.pairs_median is not None:
            out["pairs_median"] = round(self.pairs_median, 4)
        if self.reached:
            out["reached"] = self.reached
        return out


def quantile_median(quantiles: np.ndarray) -> float:
    """The median of a distribution given by its ``QUANTILE_LEVELS`` quantiles."""
    return float(np.interp(0.5, QUANTILE_LEVELS, quantiles))


def censored_quantiles(exact: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """``QUANTILE_LEVELS`` quantiles of the ratios from ``exact`` values and ``lower``
    bounds (Kaplan-Meier, redistributed to the right: each bound's weight goes equally to
    every vehicle above it, an exact value tied with a bound counting as above; what is
    above the largest exact value goes to it). Each exact value sits at the middle of its
    mass, linear in between (``np.quantile``'s "hazen", to which it reduces without
    bounds). ``exact`` must not be empty."""
    values = np.concatenate([np.asarray(exact, float), np.asarray(lower, float)])
    is_exact = np.arange(len(values)) < len(exact)
    order = np.lexsort((~is_exact, values))  # ascending; at a tie, exact first
    values, is_exact = values[order], is_exact[order]
    weight = np.ones(len(values))
    for i in np.flatnonzero(~is_exact):
        if i + 1 < len(values):
            weight[i + 1 :] += weight[i] / (len(values) - i - 1)
        else:
            weight[np.flatnonzero(is_exact)[-1]] += weight[i]
        weight[i] = 0.0
    x, w = values[is_exact], weight[is_exact]
    cum = np.cumsum(w)
    return np.interp(QUANTILE_LEVELS, (cum - w / 2.0) / cum[-1], x)


def ratio_estimate(drivers: ObservedDrivers, censoring: str = "kaplan_meier") -> RatioEstimate:
    """The drivers' ratio distribution (``censored_quantiles``), or ``DEFAULT_RATIOS``
    where fewer than ``MIN_EXACT_RATIOS`` vehicles give an exact ratio. A ratio more than
    ``OUTLIER_IQR`` interquartile ranges below the lower quartile is taken as a lower bound:
    such a driver was held back by what the free test does not see more likely than it
    wants a fifth of the limit (a drawn net's merge: 0.21 where the others' quartiles are
    0.91 and 1.07; drawn, 2.5% of the deployed drivers were slower than 0.8 of the median,
    rolling roadblocks).

    ``censoring`` (``policy.driver_ratios``): "kaplan_meier", every lower bound is one;
    "reached", those in ``drivers.reached`` count as exact ratios and the exact ratios in
    ``drivers.unsettled`` as lower bounds (module docstring)."""
    exact, lower = list(drivers.ratio.values()), list(drivers.lower.values())
    reached = 0
    if censoring == "reached":
        exact = [r for k, r in drivers.ratio.items() if k not in drivers.unsettled]
        lower = [r for k, r in drivers.ratio.items() if k in drivers.unsettled]
        exact += [r for k, r in drivers.lower.items() if k in drivers.reached]
        lower += [r for k, r in drivers.lower.items() if k not in drivers.reached]
        reached = sum(k in drivers.reached for k in drivers.lower)
    if len(exact) >= MIN_EXACT_RATIOS:
        q1, q3 = np.quantile(exact, [0.25, 0.75])
        floor = q1 - OUTLIER_IQR * (q3 - q1)
        lower += [r for r in exact if r < floor]
        exact = [r for r in exact if r >= floor]
    if len(exact) < MIN_EXACT_RATIOS:
        why = f"{len(exact)} observed vehicles cruised freely (< {MIN_EXACT_RATIOS})"
        return RatioEstimate(DEFAULT_RATIOS.copy(), len(exact), len(lower), why, reached=reached)
    return RatioEstimate(
        censored_quantiles(np.array(exact), np.array(lower)),
        len(exact),
        len(lower),
        reached=reached,
    )

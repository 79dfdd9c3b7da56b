"""The Krauss-form prior (``policy.prior = "krauss"``) as numpy, and its fit to observed pairs.

``krauss_policy_accel`` is the numpy twin of ``policy.prior.krauss_prior_accel`` (the
deployment drives with it; tests/policy/test_prior.py holds them equal): free acceleration
min(a, (V - v) / T), Gipps' safe speed behind a leader. ``calibrate_krauss`` fits it by
robust least squares as ``evaluation.idm_fit`` fits Gipps, from several starts: the min()
makes a flat in every pair where another branch binds, so one start stopped at the first
flat region (Bremen, started at a = 1.5: a = 0.39 m/s^2 at a loss 6% above that of
a = 1.9, which a profile over a found).

``fit_krauss`` guards the fit against parameters the pairs do not identify, and says which
fell back: on SUMO's ``game/ramp`` (a congested merge) the observed vehicles rarely
accelerate on a free road, and the fit took those held back by what the observation does
not see (a queue beyond the section's end, a merge) for drivers that barely accelerate:
a = 0.36 m/s^2 with a standard error of 0.04, a well-determined wrong value. The free
acceleration therefore needs ``MIN_FREE_ACCEL_PAIRS`` pairs that show it and must not
contradict most of them; a parameter without them, at a bound of the fit's range or with
a large standard error takes SUMO's default for the network's vehicle class
(``sumo_defaults``), the rest keep their fit.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from macromicro_sumo.policy.prior import EMERGENCY_DECEL_MPS2, KRAUSS_PRIOR_KEYS, RELAX_UPPER_S

# (speed_factor, a [m/s^2], b [m/s^2], tau [s], min_gap [m], relax [s]); relax's lower
# bound is the step (a car cannot close a speed gap faster than within one step).
_LOWER = np.array([0.5, 0.1, 0.5, 0.1, 0.0, 0.0])
_UPPER = np.array([1.5, 5.0, 10.0, 5.0, 20.0, RELAX_UPPER_S])
_X_SCALE = np.array([0.05, 0.5, 0.5, 0.2, 1.0, 0.5])
# Starts: every (a, T) pair, the rest at Gipps' fit's usual start.
START_ACCEL_MPS2 = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
START_RELAX_S = (1.0, 3.0)
# Robust least squares: residuals beyond it count linearly (soft L1), here and in idm_fit.
ROBUST_SCALE_MPS2 = 0.5


@dataclass(frozen=True)
class KraussParams:
    """The Krauss-form prior; desired speed V = speed_factor x local limit, gap = spacing -
    vehicle length - min_gap; the safe speed within the reaction time tau, reached within
    dt; the free term closes V - v within relax_s, at most at accel_mps2."""

    speed_factor: float
    accel_mps2: float
    decel_mps2: float
    tau_s: float
    min_gap_m: float
    relax_s: float

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


def krauss_policy_accel(
    obs: np.ndarray, p: KraussParams, veh_length_m: float, dt_s: float
) -> np.ndarray:
    """Acceleration [m/s^2] from observations (..., >= 4) [v, limit, spacing, v - v_leader]:
    min(a, (V - v) / T), or reaching -b tau + sqrt((b tau)^2 + v_l^2 + 2 b gap) within dt
    where that is smaller."""
    v, limit = obs[..., 0], obs[..., 1]
    desired = np.maximum(p.speed_factor * limit, 0.1)
    free = np.minimum(p.accel_mps2, (desired - v) / max(p.relax_s, dt_s))
    return behind_leader(obs, free, p.decel_mps2, p.tau_s, p.min_gap_m, veh_length_m, dt_s)


def behind_leader(
    obs: np.ndarray,
    free: np.ndarray,
    decel_mps2: float,
    tau_s: float,
    min_gap_m: float,
    veh_length_m: float,
    dt_s: float,
) -> np.ndarray:
    """``free`` [m/s^2], or the acceleration reaching Gipps' safe speed
    -b tau + sqrt((b tau)^2 + v_l^2 + 2 b gap) within dt where that is smaller, bounded below
    by the emergency deceleration: the numpy twin of ``policy.prior._behind_leader``, shared
    by the Gipps and Krauss-form fits."""
    v, spacing, dv = obs[..., 0], obs[..., 2], obs[..., 3]
    bt = decel_mps2 * tau_s
    gap = np.maximum(spacing - veh_length_m - min_gap_m, 0.0)
    v_leader = np.maximum(v - dv, 0.0)
    safe = -bt + np.sqrt(bt**2 + v_leader**2 + 2.0 * decel_mps2 * gap)
    return np.maximum(np.minimum(free, (safe - v) / dt_s), -EMERGENCY_DECEL_MPS2)


def calibrate_krauss(
    obs: np.ndarray, accel: np.ndarray, veh_length_m: float, dt_s: float
) -> tuple[KraussParams, float]:
    """``fit_krauss`` with a passenger car's defaults: (params, RMSE of the fitted
    accelerations [m/s^2])."""
    fit = fit_krauss(obs, accel, veh_length_m, dt_s)
    return fit.params, fit.rmse_mps2


# ---- Identification ------------------------------------------------------------------
# SUMO's defaults per vClass (sumo.dlr.de/docs/Vehicle_Type_Parameter_Defaults.html):
# (accel, decel) [m/s^2]; tau 1 s, minGap 2.5 m, speedFactor 1 for all of them. Krauss
# closes the gap to its desired speed within one step, so relax_s defaults to the step.
_VCLASS_ACCEL_DECEL = {
    "passenger": (2.6, 4.5),
    "private": (2.6, 4.5),
    "taxi": (2.6, 4.5),
    "evehicle": (2.6, 4.5),
    "delivery": (2.6, 4.5),
    "truck": (1.3, 4.0),
    "trailer": (1.1, 4.0),
    "bus": (1.2, 4.0),
    "coach": (2.0, 4.0),
    "motorcycle": (6.0, 10.0),
    "moped": (1.1, 7.0),
}
# A pair shows free acceleration when its leader is at least FREE_HEADWAY_S at its own
# speed plus FREE_GAP_M ahead (env.driver_speed's free test), it is below 0.9 x the fitted
# desired speed, and it accelerates at >= FREE_ACCEL_MPS2 (Krauss at SUMO's defaults:
# a (1 - sigma U) >= 1.3 m/s^2; dawdling back to a cruising speed gives less).
FREE_HEADWAY_S = 2.0
FREE_GAP_M = 10.0
FREE_ROOM = 0.9
FREE_ACCEL_MPS2 = 1.0
# ... and a needs this many of them (100 s of accelerating vehicles at 0.5 s steps):
# Bremen's pairs have 1,145 of 15,193, SUMO's game/ramp 85 of 1,524 (there 448 free pairs
# below 0.9 V average 0.00 m/s^2, where Bremen's average 1.02).
MIN_FREE_ACCEL_PAIRS = 200
# The Krauss form never accelerates faster than a: where most free-acceleration pairs
# accelerate faster than the fit allows (beyond ROBUST_SCALE_MPS2), a was decided by other
# pairs, held back by what the observation does not see (share of them above the fit:
# Bremen 24%; a drawn net with its queue at the entry, a = 0.70 m/s^2, 82%; SUMO's
# game/ramp, a = 0.36, 100%).
MAX_BEYOND_SHARE = 0.5
# A fitted parameter whose standard error (Gauss-Newton, at the solution) exceeds this
# share of its value is not identified by the pairs.
MAX_RELATIVE_SE = 0.25
_NAMES = ("speed_factor", "accel_mps2", "decel_mps2", "tau_s", "min_gap_m", "relax_s")
_SPEED, _ACCEL, _TAU, _MIN_GAP, _RELAX = 0, 1, 3, 4, 5
# Gipps' safe speed's parameters (b, tau, min_gap): no gradient where it binds on no pair.
_INTERACTION = (2, 3, 4)
# ``binding_start``: the share of following pairs on which the safe speed binds at its tau.
BINDING_QUANTILE = 0.1


def sumo_defaults(vclass: str = "passenger") -> KraussParams:
    """SUMO's Krauss defaults for ``vclass`` (a passenger car's for a class not listed);
    relax_s 0 stands for the step (Krauss' own free term)."""
    a, b = _VCLASS_ACCEL_DECEL.get(vclass, _VCLASS_ACCEL_DECEL["passenger"])
    return KraussParams(1.0, a, b, 1.0, 2.5, 0.0)


def network_defaults(vtypes: pd.DataFrame) -> KraussParams:
    """``sumo_defaults`` of the vClass most of a ground truth's vehicles have
    (``vtypes.csv``: vclass, vehicles)."""
    if vtypes.empty or "vclass" not in vtypes:
        return sumo_defaults()
    counts = vtypes.groupby("vclass")["vehicles"].sum()
    return sumo_defaults(str(counts.idxmax()))


@dataclass(frozen=True)
class KraussFit:
    """A guarded fit (``fit_krauss``): the parameters, the RMSE of the fitted accelerations
    [m/s^2], the pairs showing free acceleration, and per parameter that fell back to
    ``defaults`` why, and per parameter refitted after another fell back why."""

    params: KraussParams
    rmse_mps2: float
    free_accel_pairs: int
    fallback: dict[str, str] = field(default_factory=dict)
    defaults: KraussParams | None = None
    refitted: dict[str, str] = field(default_factory=dict)

    @property
    def fitted(self) -> tuple[str, ...]:
        return tuple(n for n in _NAMES if n not in self.fallback)

    def prior_params(self, veh_length_m: float, dt_s: float) -> dict[str, float]:
        """The agent's prior buffer (``policy.prior.KRAUSS_PRIOR_KEYS``, in its order)."""
        p = {**self.params.as_dict(), "veh_length_m": float(veh_length_m), "dt_s": float(dt_s)}
        return {k: p[k] for k in KRAUSS_PRIOR_KEYS}

    def record(self) -> dict[str, object]:
        """What a policy manifest records of the fit besides the parameters."""
        return {
            "fitted": list(self.fitted),
            "fallback": dict(self.fallback),
            "free_accel_pairs": self.free_accel_pairs,
            "defaults": None if self.defaults is None else self.defaults.as_dict(),
            "refitted": dict(self.refitted),
        }


def free_accel_mask(obs: np.ndarray, accel: np.ndarray, speed_factor: float) -> np.ndarray:
    """(N,) bool: the pairs that show free acceleration (``FREE_HEADWAY_S`` ..
    ``FREE_ACCEL_MPS2``) below ``FREE_ROOM`` x the desired speed ``speed_factor`` x limit."""
    v, limit, spacing = obs[:, 0], obs[:, 1], obs[:, 2]
    free = spacing >= v * FREE_HEADWAY_S + FREE_GAP_M
    room = v <= FREE_ROOM * speed_factor * limit
    return free & room & (accel >= FREE_ACCEL_MPS2)


def _beyond(
    obs: np.ndarray, accel: np.ndarray, x: np.ndarray, veh_length_m: float, dt_s: float
) -> float:
    """The share of pairs accelerating faster than parameters ``x`` allow (beyond the
    robust scale)."""
    fitted = krauss_policy_accel(obs, KraussParams(*x), veh_length_m, dt_s)
    return float(np.mean(accel > fitted + ROBUST_SCALE_MPS2))


def fit_krauss(
    obs: np.ndarray,
    accel: np.ndarray,
    veh_length_m: float,
    dt_s: float,
    defaults: KraussParams | None = None,
    fixed: dict[str, str] | None = None,
    dawdle_sigma: float = 0.0,
) -> KraussFit:
    """Robust least-squares fit (soft L1) of (speed_factor, a, b, tau, min_gap, relax) to
    observed pairs, the best of ``START_ACCEL_MPS2`` x ``START_RELAX_S`` starts, with the
    parameters the pairs do not identify at ``defaults`` (``sumo_defaults()`` if None):
    a without ``MIN_FREE_ACCEL_PAIRS`` free-acceleration pairs or where more than
    ``MAX_BEYOND_SHARE`` of them accelerate faster than the fit allows (then relax_s too
    if, with the default a, they still do); any parameter at a bound of the fit's range or
    with a standard error above ``MAX_RELATIVE_SE`` of its value. Not relax_s at a bound:
    at the step it is Krauss' own free term, at its upper bound the drivers' neutral
    cruising at their own speed (docs/deploy-log.md), which Stage II replaces by a relaxation
    chosen on the training runs' loops (``policy.relax_choice``); nor min_gap_m at 0.

    Where a falls back, relax_s is refitted alone (``_refit_relax``, recorded in
    ``KraussFit.refitted``): the full fit chose it next to the rejected a. The others keep
    their values of the full fit, not refitted: on game/ramp's pairs, with
    a at its default the refit drove relax_s to its bound (10 s) and the speed factor from
    0.82 to 0.68, slowing every free car as a = 0.36 had; on netgen_corridor's, with a and
    relax_s at theirs, b fell from 4.57 to 0.55 m/s^2. In the Krauss form each pair's
    residual depends only on the branch of the min() that binds, so the interaction
    parameters (b, tau, min_gap) are fitted on pairs the free term's do not decide.

    ``dawdle_sigma`` > 0: where a falls back, relax_s is refitted next to SUMO's dawdled
    mean a (1 - sigma / 2) (``dawdled_mean_accel``), the a the deployment drives a fallen-back
    prior with where it dawdles the commands (``deploy.command_dawdle``), not next to a
    itself; the prior keeps a, whose fallback the deployment's dawdle reads. Why: the pairs of
    SUMO's dawdling drivers accelerate at about that mean, and a relaxation fitted next to the
    undawdled 2.6 lengthens until (V - v) / T matches it well below V. Drawn arterial 1706's
    pairs: 3.43 s next to 2.6, 0.61 s next to 1.95; its deployed cars then accelerated at
    0.44 m/s^2 at 8-10 m/s, the truth's at 1.08 (docs/deploy-log.md, stop 51, hP51).

    ``fixed`` (name: why) are held at ``defaults`` throughout, the others fitted beside them:
    the speed factor where the drivers' desired-speed ratios fell back to SUMO's
    (``env.driver_speed_ratios.ratio_estimate``; on game/ramp fitted 0.82 where SUMO's cars have 1.0;
    where a or the speed factor falls back, relax_s is refitted alone)."""
    defaults = defaults or sumo_defaults()
    lower = _LOWER.copy()
    lower[5] = dt_s
    default_x = np.clip(np.array([getattr(defaults, n) for n in _NAMES], float), lower, _UPPER)
    pinned = {_NAMES.index(n): float(default_x[_NAMES.index(n)]) for n in (fixed or {})}
    x, rmse, se = krauss_least_squares(obs, accel, veh_length_m, dt_s, pinned)
    free = free_accel_mask(obs, accel, float(x[0]))
    free_pairs = int(free.sum())
    fallback = {i: why for i, why in _unidentified(x, se, lower).items() if i not in pinned}
    fallback.update({_NAMES.index(n): why for n, why in (fixed or {}).items()})
    fitted_a = float(x[_ACCEL])
    if free_pairs < MIN_FREE_ACCEL_PAIRS:
        fallback[_ACCEL] = (
            f"{free_pairs} pairs show free acceleration (< {MIN_FREE_ACCEL_PAIRS}); "
            f"fitted {x[_ACCEL]:.3g} m/s^2"
        )
    elif (share := _beyond(obs[free], accel[free], x, veh_length_m, dt_s)) > MAX_BEYOND_SHARE:
        fallback[_ACCEL] = (
            f"{share:.0%} of the {free_pairs} free-acceleration pairs accelerate faster than "
            f"the fit allows; fitted {x[_ACCEL]:.3g} m/s^2"
        )
    x = x.copy()
    x[list(fallback)] = default_x[list(fallback)]
    refitted = {}
    if _ACCEL in fallback or (_SPEED in fallback and _SPEED not in pinned):
        kept, beside = x[_RELAX], x.copy()
        if _ACCEL in fallback and dawdle_sigma > 0.0:
            beside[_ACCEL] = dawdled_mean_accel(x[_ACCEL], dawdle_sigma)
        x[_RELAX] = _refit_relax(obs, accel, beside, veh_length_m, dt_s, lower[_RELAX])
        which = "a" if _ACCEL in fallback else "the speed factor"
        dawdled = f" (dawdled at sigma {dawdle_sigma:g})" if beside[_ACCEL] != x[_ACCEL] else ""
        refitted[_RELAX] = (
            f"{which} fell back: refitted alone with a = {beside[_ACCEL]:.3g} m/s^2{dawdled}, "
            f"speed factor {x[_SPEED]:.3g} (fitted {kept:.3g} s next to a = {fitted_a:.3g})"
        )
    if _ACCEL in fallback and free_pairs >= MIN_FREE_ACCEL_PAIRS:
        share = _beyond(obs[free], accel[free], x, veh_length_m, dt_s)
        if share > MAX_BEYOND_SHARE:  # the relaxation holds them back as a did
            fallback[_RELAX] = f"{share:.0%} of them still faster with the default a"
            refitted.pop(_RELAX, None)
            x[_RELAX] = default_x[_RELAX]
    if fallback:
        fitted = krauss_policy_accel(obs, KraussParams(*x), veh_length_m, dt_s)
        rmse = float(np.sqrt(np.mean((fitted - accel) ** 2)))
    why = {_NAMES[i]: fallback[i] for i in sorted(fallback)}
    again = {_NAMES[i]: why_ for i, why_ in refitted.items()}
    return KraussFit(KraussParams(*map(float, x)), rmse, free_pairs, why, defaults, again)


def dawdled_mean_accel(accel_mps2: float, sigma: float) -> float:
    """SUMO's Krauss driver's mean free acceleration [m/s^2] at a = ``accel_mps2`` and
    imperfection ``sigma``, a (1 - sigma / 2) (``deploy.safety.dawdled_accel`` from v = a
    on): 1.95 at SUMO's defaults."""
    return float(accel_mps2) * (1.0 - 0.5 * float(sigma))


def _refit_relax(
    obs: np.ndarray,
    accel: np.ndarray,
    x: np.ndarray,
    veh_length_m: float,
    dt_s: float,
    lower_s: float,
) -> float:
    """relax_s [s] fitted alone (soft L1, the best of ``START_RELAX_S`` and its kept value as
    starts) with the other parameters at ``x``: the full fit chose it next to the rejected
    a, on the pairs within a x relax_s of their desired speed (on netgen_corridor's, a = 0.1
    at its bound, relax_s 1.31 s; alone with a = 2.6: 10 s, fit RMSE 1.46 -> 0.42 m/s^2)."""

    def resid(t: np.ndarray) -> np.ndarray:
        p = KraussParams(*x[:_RELAX], float(t[0]))
        return krauss_policy_accel(obs, p, veh_length_m, dt_s) - accel

    best = None
    for t0 in (*START_RELAX_S, float(x[_RELAX])):
        fit = least_squares(
            resid,
            [float(np.clip(t0, lower_s, _UPPER[_RELAX]))],
            bounds=([lower_s], [_UPPER[_RELAX]]),
            x_scale=[_X_SCALE[_RELAX]],
            loss="soft_l1",
            f_scale=ROBUST_SCALE_MPS2,
        )
        if best is None or fit.cost < best.cost:
            best = fit
    assert best is not None
    return float(best.x[0])


def _unidentified(x: np.ndarray, se: np.ndarray, lower: np.ndarray) -> dict[int, str]:
    """Parameters at a bound of the fit's range or with a large standard error, and why
    (relax_s and min_gap_m at 0 excepted: ``fit_krauss``)."""
    out = {}
    tol = 1e-3 * (_UPPER - _LOWER)
    for i in range(len(_NAMES)):
        if i == _RELAX or (i == _MIN_GAP and x[i] < tol[i]):
            continue
        if x[i] - lower[i] < tol[i] or _UPPER[i] - x[i] < tol[i]:
            out[i] = f"at its bound ({x[i]:.3g}, fit range {lower[i]:.3g}-{_UPPER[i]:.3g})"
        elif se[i] > MAX_RELATIVE_SE * abs(x[i]):
            out[i] = f"standard error {se[i]:.3g} > {MAX_RELATIVE_SE:.0%} of {x[i]:.3g}"
    return out


def krauss_least_squares(
    obs: np.ndarray,
    accel: np.ndarray,
    veh_length_m: float,
    dt_s: float,
    pinned: dict[int, float] | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """The unguarded fit, the best of the multi-start fits: (parameters in ``KraussParams``'
    order, RMSE [m/s^2], their standard errors); ``pinned`` (index: value) held at their
    values (bounds a hair apart: least_squares needs lower < upper). Where the best leaves
    Gipps' safe speed binding on no pair (b, tau and min_gap all without a standard error),
    one more start from it with tau where the safe speed binds (``binding_start``), kept if
    its cost is lower."""
    lower = _LOWER.copy()
    lower[5] = dt_s
    upper = _UPPER.copy()
    for i, value in (pinned or {}).items():
        lower[i], upper[i] = value - 1e-9, value + 1e-9

    def resid(x: np.ndarray) -> np.ndarray:
        return krauss_policy_accel(obs, KraussParams(*x), veh_length_m, dt_s) - accel

    def solve(x0: np.ndarray) -> Any:
        return least_squares(
            resid,
            np.clip(x0, lower, upper),
            bounds=(lower, upper),
            x_scale=_X_SCALE,
            loss="soft_l1",
            f_scale=ROBUST_SCALE_MPS2,
        )

    best = None
    for a0 in START_ACCEL_MPS2:
        for t0 in START_RELAX_S:
            fit = solve(np.array([1.0, a0, 4.0, 1.0, 2.0, t0]))
            if best is None or fit.cost < best.cost:
                best = fit
    assert best is not None
    # A pinned parameter is no unknown: its column would inflate the others' errors.
    free = np.array([i not in (pinned or {}) for i in range(len(_NAMES))])
    se = np.zeros(len(_NAMES))
    se[free] = _standard_errors(best.jac[:, free], best.cost, len(accel))
    interaction = [i for i in _INTERACTION if free[i]]
    if interaction and np.isinf(se[interaction]).all():
        x0 = binding_start(obs, best.x, veh_length_m, lower, upper)
        if x0 is not None and (again := solve(x0)).cost < best.cost:
            best = again
            se[free] = _standard_errors(best.jac[:, free], best.cost, len(accel))
    return best.x, float(np.sqrt(np.mean(best.fun**2))), se


def binding_start(
    obs: np.ndarray, x: np.ndarray, veh_length_m: float, lower: np.ndarray, upper: np.ndarray
) -> np.ndarray | None:
    """``x`` with tau [s] at the ``BINDING_QUANTILE`` of the following pairs' time gaps
    ((spacing - length - min_gap) / v; a leader nearer than ``FREE_HEADWAY_S`` x v +
    ``FREE_GAP_M``), so that Gipps' safe speed binds on the closest followers; None where
    no pair follows or that tau is outside the fit's range.

    Why: every start has tau = 1 s, b = 4 m/s^2, min_gap = 2 m; where the observed drivers
    all keep more than 1 s (IDM cars in steady traffic, ring_two_lane: 1.55 s at the 1st
    percentile), the safe speed binds on no pair, the three have no gradient and stay at
    their starts (standard error inf), and the guard gave them SUMO's defaults, a prior
    that follows at 1 s (docs/deploy-log.md, "ring_two_lane (stop 29)")."""
    v, spacing = obs[:, 0], obs[:, 2]
    near = (v > 1.0) & (spacing < v * FREE_HEADWAY_S + FREE_GAP_M)
    if not near.any():
        return None
    gaps_s = (spacing[near] - veh_length_m - x[_MIN_GAP]) / v[near]
    tau0 = float(np.quantile(gaps_s, BINDING_QUANTILE))
    if not lower[_TAU] < tau0 < upper[_TAU]:
        return None
    out = x.copy()
    out[_TAU] = tau0
    return out


def _standard_errors(jac: np.ndarray, cost: float, pairs: int) -> np.ndarray:
    """Gauss-Newton standard errors at the solution (``jac`` is the robust loss's weighted
    Jacobian); infinite for a parameter in a direction no pair informs (a zero eigenvalue
    of J'J: a pseudo-inverse would call it exact)."""
    w, vec = np.linalg.eigh(jac.T @ jac)
    flat = w <= max(float(w.max()), 0.0) * 1e-12
    var = (vec[:, ~flat] ** 2 / w[~flat]).sum(axis=1) * (2.0 * cost / max(pairs - len(w), 1))
    var[(vec[:, flat] ** 2 > 1e-6).any(axis=1)] = np.inf
    return np.sqrt(var)

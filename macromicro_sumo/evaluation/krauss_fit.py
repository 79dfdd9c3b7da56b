"""The Krauss-form prior (``policy.prior = "krauss"``) as numpy, and its fit to observed pairs.

``krauss_policy_accel`` is the numpy twin of ``policy.prior.krauss_prior_accel`` (the
deployment drives with it; tests/policy/test_prior.py holds them equal): free acceleration
min(a, (V - v) / T), Gipps' safe speed behind a leader. ``calibrate_krauss`` fits it by
robust least squares as ``evaluation.idm_fit`` fits Gipps, from several starts: the min()
makes a flat in every pair where another branch binds, so one start stopped at the first
flat region (Bremen, started at a = 1.5: a = 0.39 m/s^2 at a loss 6% above that of
a = 1.9, which a profile over a found).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import least_squares

from macromicro_sumo.policy.prior import EMERGENCY_DECEL_MPS2

# (speed_factor, a [m/s^2], b [m/s^2], tau [s], min_gap [m], relax [s]); relax's lower
# bound is the step (a car cannot close a speed gap faster than within one step).
_LOWER = np.array([0.5, 0.1, 0.5, 0.1, 0.0, 0.0])
_UPPER = np.array([1.5, 5.0, 10.0, 5.0, 20.0, 10.0])
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
    """Robust least-squares fit (soft L1) of (speed_factor, a, b, tau, min_gap, relax) to
    observed pairs, the best of ``START_ACCEL_MPS2`` x ``START_RELAX_S`` starts; returns
    (params, RMSE of the fitted accelerations)."""
    lower = _LOWER.copy()
    lower[5] = dt_s

    def resid(x: np.ndarray) -> np.ndarray:
        return krauss_policy_accel(obs, KraussParams(*x), veh_length_m, dt_s) - accel

    best = None
    for a0 in START_ACCEL_MPS2:
        for t0 in START_RELAX_S:
            x0 = np.clip(np.array([1.0, a0, 4.0, 1.0, 2.0, t0]), lower, _UPPER)
            fit = least_squares(
                resid,
                x0,
                bounds=(lower, _UPPER),
                x_scale=_X_SCALE,
                loss="soft_l1",
                f_scale=ROBUST_SCALE_MPS2,
            )
            if best is None or fit.cost < best.cost:
                best = fit
    assert best is not None
    return KraussParams(*best.x), float(np.sqrt(np.mean(best.fun**2)))

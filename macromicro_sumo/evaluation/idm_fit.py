"""IDM as a driving policy: the classical baseline a traffic engineer would calibrate.

``idm_policy`` turns IDM parameters into the same kind of action (acceleration from the
observation [v, v_limit, spacing, v - v_leader]) as the learned policy, so both drive the
hidden vehicles through the same speed-command path. ``calibrate_idm`` fits one shared
parameter set to observed (observation, action) pairs by least squares (scipy).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import least_squares

from macromicro_sumo.road.physics import idm_accel


@dataclass(frozen=True)
class IdmParams:
    """IDM parameters; desired speed = speed_factor x local limit. Arrays or scalars."""

    speed_factor: np.ndarray | float
    tau_s: np.ndarray | float
    accel_mps2: np.ndarray | float
    decel_mps2: np.ndarray | float
    min_gap_m: np.ndarray | float
    delta: float = 4.0

    def as_dict(self) -> dict[str, float]:
        return {k: np.asarray(v).tolist() for k, v in asdict(self).items()}


def idm_policy_accel(obs: np.ndarray, p: IdmParams, veh_length_m: float) -> np.ndarray:
    """IDM acceleration [m/s^2] from observations (..., 4)."""
    v, limit, spacing, dv = obs[..., 0], obs[..., 1], obs[..., 2], obs[..., 3]
    desired = np.maximum(np.asarray(p.speed_factor) * limit, 0.1)
    return idm_accel(
        v,
        spacing - veh_length_m,
        dv,
        desired,
        p.tau_s,
        p.accel_mps2,
        p.decel_mps2,
        p.min_gap_m,
        p.delta,
    )


_LOWER = np.array([0.5, 0.3, 0.1, 0.1, 0.0])
_UPPER = np.array([1.5, 5.0, 5.0, 10.0, 20.0])


def calibrate_idm(
    obs: np.ndarray, accel: np.ndarray, veh_length_m: float, delta: float = 4.0
) -> tuple[IdmParams, float]:
    """Least-squares fit of (speed_factor, T, a, b, s0) to observed pairs; returns (params, RMSE)."""

    def resid(x: np.ndarray) -> np.ndarray:
        p = IdmParams(*x, delta=delta)
        return idm_policy_accel(obs, p, veh_length_m) - accel

    x0 = np.array([0.95, 1.5, 1.0, 1.5, 2.0])
    fit = least_squares(
        resid, x0, bounds=(_LOWER, _UPPER), x_scale=np.array([0.05, 0.5, 0.5, 0.5, 1.0])
    )
    p = IdmParams(*fit.x, delta=delta)
    return p, float(np.sqrt(np.mean(fit.fun**2)))

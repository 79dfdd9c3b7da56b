"""A textbook reference on a single-lane ring, for tests only: arc-order leaders and an Euler
IDM rollout that SUMO's IDM is checked against (tests/truth/test_ring_truth.py)."""

from __future__ import annotations

import numpy as np

from macromicro_sumo.road.physics import idm_accel


def ring_leaders(arc_m: np.ndarray, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Leader index and front-to-front spacing [m] of every vehicle on a ring.

    ``arc_m`` has shape (..., N). The leader is the next vehicle ahead in arc order; the
    spacings of one ring sum to ``length_m``. Works on batches (leading dimensions).
    """
    s = np.mod(arc_m, length_m)
    order = np.argsort(s, axis=-1, kind="stable")
    ahead = np.roll(order, -1, axis=-1)
    leader = np.empty_like(order)
    np.put_along_axis(leader, order, ahead, axis=-1)
    s_leader = np.take_along_axis(s, leader, axis=-1)
    spacing = np.mod(s_leader - s, length_m)
    # Two vehicles at the same point: the spacing is 0, not L.
    return leader, spacing


def sorted_spacings(arc_m: np.ndarray, length_m: float) -> np.ndarray:
    """Spacings between consecutive vehicles in arc order, shape (..., N); they sum to L."""
    s = np.sort(np.mod(arc_m, length_m), axis=-1)
    return np.diff(np.concatenate([s, s[..., :1] + length_m], axis=-1), axis=-1)


def simulate_idm_ring(
    arc0_m: np.ndarray,
    speed0_mps: np.ndarray,
    length_m: float,
    veh_length_m: float,
    params: dict[str, np.ndarray],
    dt_s: float,
    n_steps: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Euler rollout of IDM vehicles on a ring with a uniform desired speed per vehicle.

    Matches SUMO's update with one IDM iteration per step: v' = max(0, v + a dt),
    x' = x + v' dt. Returns (arc positions, speeds), each of shape (n_steps + 1, N).
    """
    arc = np.empty((n_steps + 1, len(arc0_m)))
    speed = np.empty_like(arc)
    arc[0], speed[0] = arc0_m, speed0_mps
    for t in range(n_steps):
        leader, spacing = ring_leaders(arc[t], length_m)
        gap = spacing - veh_length_m
        a = idm_accel(
            speed[t],
            gap,
            speed[t] - speed[t][leader],
            params["desired_speed_mps"],
            params["tau_s"],
            params["accel_mps2"],
            params["decel_mps2"],
            params["min_gap_m"],
            params.get("delta", 4.0),
        )
        speed[t + 1] = np.maximum(0.0, speed[t] + a * dt_s)
        arc[t + 1] = arc[t] + speed[t + 1] * dt_s
    return arc, speed

"""Stage II: a physical prior under the learned policy (``policy.prior``).

With ``policy.prior = "idm"`` the policy's mean action is the IDM's acceleration on the raw
observation plus the actor's output (residual policy learning): the IDM's parameters are
fitted to the training runs' observed pairs before training (``evaluation.idm_fit.
calibrate_idm``, by the stage) and stay fixed. Why: SUMO's recorded accelerations are noisy
and close-following states rare in the observed pairs, so an MLP alone learned a mean that
barely reacts to spacing (Bremen: -1.00 m/s^2 at 51 m and -0.96 at 5 m, closing at 6 m/s)
and collided or jammed when deployed; the IDM reacts to spacing by construction and the
residual only corrects it where the data say so.

``idm_prior_accel`` is ``evaluation.idm_fit.idm_policy_accel`` on torch tensors (the same
gap floor and braking bound: tests/policy/test_prior.py compares them); the parameters are
buffers of the agent (``IDM_PRIOR_KEYS``), so they travel in the checkpoint's state_dict.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

PRIORS = ("none", "idm")
# The agent's buffers, in this order: desired speed = speed_factor x the local limit.
IDM_PRIOR_KEYS = (
    "speed_factor",
    "tau_s",
    "accel_mps2",
    "decel_mps2",
    "min_gap_m",
    "delta",
    "veh_length_m",
)
# As evaluation.idm_fit (a policy module may not import evaluation; the test checks they agree):
# a car brakes no harder than SUMO's emergencyDecel default, a gap is never below 0.1 m.
EMERGENCY_DECEL_MPS2 = 9.0
MIN_GAP_M = 0.1


def idm_prior_params(params: Mapping[str, float], veh_length_m: float) -> dict[str, float]:
    """The prior's buffer values from IDM parameters (``IdmParams.as_dict()``) and the
    vehicle length the fit used."""
    out = {k: float(params[k]) for k in IDM_PRIOR_KEYS if k != "veh_length_m"}
    out["veh_length_m"] = float(veh_length_m)
    return out


def idm_prior_accel(obs: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """IDM acceleration [m/s^2] from raw observations (..., D) whose first four features are
    [v, v_limit, spacing, v - v_leader] (both observation kinds)."""
    v, limit, spacing, dv = obs[..., 0], obs[..., 1], obs[..., 2], obs[..., 3]
    desired = torch.clamp(p["speed_factor"] * limit, min=0.1)
    gap = torch.clamp(spacing - p["veh_length_m"], min=MIN_GAP_M)
    a, b = p["accel_mps2"], p["decel_mps2"]
    s_star = p["min_gap_m"] + torch.clamp(
        v * p["tau_s"] + v * dv / (2.0 * torch.sqrt(a * b)), min=0.0
    )
    free = 1.0 - (v / desired) ** p["delta"]
    return torch.clamp(a * (free - (s_star / gap) ** 2), min=-EMERGENCY_DECEL_MPS2)

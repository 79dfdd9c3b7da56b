"""Stage II: a physical prior under the learned policy (``policy.prior``).

With ``policy.prior = "idm"`` or ``"gipps"`` the policy's mean action is the prior's
acceleration on the raw observation plus the actor's bounded output (residual policy
learning): the prior's parameters are fitted to the training runs' observed pairs before
training (``evaluation.idm_fit.fit_policy_prior``, by the stage) and stay fixed. Why:
SUMO's recorded accelerations are noisy and close-following states rare in the observed
pairs, so an MLP alone learned a mean that barely reacts to spacing (Bremen: -1.00 m/s^2 at
51 m and -0.96 at 5 m, closing at 6 m/s) and collided or jammed when deployed; a
car-following model reacts to spacing by construction and the residual only corrects it
where the data say so.

* ``idm``: the Intelligent Driver Model. It plans to stop comfortably (at b) for whatever
  stands ahead: for the end of an on-ramp's acceleration lane, a standing leader, from
  ~250 m at 30 m/s, so deployed ramp vehicles crawled to the lane end and jammed the merge
  (Bremen: merge lanes at 4-8 m/s against the truth's 28).
* ``gipps``: Gipps' model (Gipps 1981; Treiber & Kesting, "Traffic Flow Dynamics",
  ch. 11.2), Krauss' ancestor: accelerate freely, 2.5 a (1 - v/V) sqrt(0.025 + v/V), unless
  that is faster than the safe speed behind the leader, -b tau + sqrt((b tau)^2 + v_l^2 +
  2 b gap) (the leader assumed to brake as hard), which it then takes within the step dt.
  It brakes only as late as is safe, as SUMO's drivers do.
* ``krauss``: Gipps' safe speed under a Krauss-form free term (Krauss 1998, SUMO's default
  model): accelerate at a until the desired speed is near, then close the rest within the
  relaxation time T, min(a, (V - v) / T). Gipps' free term tapers from half-way to V (at
  v = 0.75 V it is 0.55 a), which left Bremen's deployed cars entering at 33 m/s 3-5 m/s
  behind SUMO's, which accelerate at ~1.9 m/s^2 up to their desired speed. Its parameters
  that the pairs do not identify take SUMO's defaults for the network's vClass
  (``evaluation.krauss_fit.fit_krauss``; the policy manifest says which and why).

The torch functions here equal ``evaluation.idm_fit``'s numpy ones (the same gap floor and
braking bound: tests/policy/test_prior.py compares them); the parameters are buffers of the
agent (``PRIOR_KEYS``), so they travel in the checkpoint's state_dict.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch

PRIORS = ("none", "idm", "gipps", "krauss")
# The agent's buffers per prior, in this order: desired speed = speed_factor x the local limit.
IDM_PRIOR_KEYS = (
    "speed_factor",
    "tau_s",
    "accel_mps2",
    "decel_mps2",
    "min_gap_m",
    "delta",
    "veh_length_m",
)
GIPPS_PRIOR_KEYS = (
    "speed_factor",
    "accel_mps2",
    "decel_mps2",
    "tau_s",
    "min_gap_m",
    "veh_length_m",
    "dt_s",
)
KRAUSS_PRIOR_KEYS = (*GIPPS_PRIOR_KEYS, "relax_s")
PRIOR_KEYS = {"idm": IDM_PRIOR_KEYS, "gipps": GIPPS_PRIOR_KEYS, "krauss": KRAUSS_PRIOR_KEYS}


def prior_buffer(agent) -> dict[str, float]:
    """An agent's prior parameters by name (its ``<prior>_prior`` buffer, ``PRIOR_KEYS``'
    order), as float64: what the numpy twins of the prior (the deployment's, the
    evaluation's) are built from."""
    values = getattr(agent, f"{agent.prior}_prior").detach().double().tolist()
    return dict(zip(PRIOR_KEYS[agent.prior], values, strict=True))


# Shared with evaluation.idm_fit and krauss_fit, which import them (the numpy twins): a car
# brakes no harder than SUMO's emergencyDecel default, a gap is never below 0.1 m.
EMERGENCY_DECEL_MPS2 = 9.0
MIN_GAP_M = 0.1
# The Krauss form's relaxation time's upper bound [s] in its fit (evaluation.krauss_fit):
# a fit there is the pairs' neutral cruising, not an identified value (policy.relax_choice).
RELAX_UPPER_S = 10.0


def idm_prior_params(params: Mapping[str, float], veh_length_m: float) -> dict[str, float]:
    """The IDM prior's buffer values from IDM parameters (``IdmParams.as_dict()``) and the
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


def gipps_prior_accel(obs: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """Gipps' acceleration [m/s^2] from raw observations (..., D) as ``idm_prior_accel``'s:
    the free acceleration or the one reaching the safe speed within dt, the smaller."""
    v, limit = obs[..., 0], obs[..., 1]
    ratio = torch.clamp(v / torch.clamp(p["speed_factor"] * limit, min=0.1), min=0.0)
    free = 2.5 * p["accel_mps2"] * (1.0 - ratio) * torch.sqrt(0.025 + ratio)
    return _behind_leader(obs, p, free)


def krauss_prior_accel(obs: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """The Krauss-form prior's acceleration [m/s^2] from raw observations (..., D) as
    ``idm_prior_accel``'s: min(a, (V - v) / T), or Gipps' safe speed within dt where smaller."""
    v, limit = obs[..., 0], obs[..., 1]
    desired = torch.clamp(p["speed_factor"] * limit, min=0.1)
    free = torch.minimum(p["accel_mps2"], (desired - v) / p["relax_s"])
    return _behind_leader(obs, p, free)


def _behind_leader(
    obs: torch.Tensor, p: Mapping[str, torch.Tensor], free: torch.Tensor
) -> torch.Tensor:
    """``free`` [m/s^2], or the acceleration reaching Gipps' safe speed within dt where that
    is smaller, bounded below by the emergency deceleration."""
    v, spacing, dv = obs[..., 0], obs[..., 2], obs[..., 3]
    bt = p["decel_mps2"] * p["tau_s"]
    gap = torch.clamp(spacing - p["veh_length_m"] - p["min_gap_m"], min=0.0)
    v_leader = torch.clamp(v - dv, min=0.0)
    safe = -bt + torch.sqrt(bt**2 + v_leader**2 + 2.0 * p["decel_mps2"] * gap)
    accel = torch.minimum(free, (safe - v) / p["dt_s"])
    return torch.clamp(accel, min=-EMERGENCY_DECEL_MPS2)


PRIOR_ACCEL: dict[str, Callable[[torch.Tensor, Mapping[str, torch.Tensor]], torch.Tensor]] = {
    "idm": idm_prior_accel,
    "gipps": gipps_prior_accel,
    "krauss": krauss_prior_accel,
}

"""Stage II: a residual policy corrects its prior only where a leader matters and where
its training pairs are (``policy.residual``).

With ``policy.prior`` the policy's mean is a fitted car-following model plus the actor's
bounded residual (``policy.agent``). Two trainings of netgen_corridor on one ground truth
and generator, PPO seeds 1 and 2, deployed at 18% and 82% speed-within-5% (docs/deploy-log.md,
"Measured"). Three causes, measured there:

* Neutral cruising. On a free road the recorded accelerations average 0 at every cruising
  speed (limit 24.45 m/s: -0.01 m/s^2 from 18 to 24 m/s): each driver keeps its own
  desired speed, which the observation does not carry. A residual fitted to them cancels
  the prior's pull towards its desired speed (Gipps: ~0.03 m/s^2 per m/s), so the deployed
  cruising speed drifts with whatever small bias the residual keeps: 0.1 m/s^2 moves it by
  ~3 m/s. The residual is therefore fitted only on pairs outside the prior's free regime
  (``free_regime``: a leader changes the prior's acceleration); the free regime is the
  prior's.
* Extrapolation. The pairs cover own speeds of 16-33 m/s; below, the zero-initialised MLP
  extended its trend to -0.5 to -0.8 m/s^2 at a standstill, against Gipps' free
  acceleration of 0.1-0.3 m/s^2 there: a vehicle that braked below ~15 m/s (a lane drop)
  never sped up again (55% of the deployed vehicle-steps at 5-10 m/s).
  ``anchor_loss`` holds the residual at 0 off the pairs and in the free regime:
  pseudo-pairs whose recorded action is the prior's, at the pairs' states with the own
  speed redrawn from 0 to 1.2 x the fastest (``anchor_observations``), weighted by how far
  outside the pairs' per-feature range they lie (``support_weight``) or 1 when free.
  Where every pair is free none is fitted, and the anchors alone hold the residual
  (``policy.ppo``); without them the policy gradient alone shaped it, its own way per
  PPO seed (the paper's ring until stop 27: leader-follower RMSE 0.17-0.33 / 0.23-0.35
  m/s over six seeds; docs/design.md).
* Pairs that answer another scene. In the rollouts 87% of the observed pairs had a hidden,
  generated leader; behind a generated slow vehicle the prior brakes at -9 m/s^2 where the
  recorded action (which answered the true leader) was ~0. The likelihood per pair was
  -3.6 to -7.9 at update 1 (-14.6 in an earlier training) and the state-independent std
  grew to 1.2-2.5 m/s^2 fitting those, which weakened the likelihood against PPO's noisy
  policy gradient (a residual's gradient scales as 1 / std^2 in the likelihood, 1 / std
  in PPO). ``policy.ppo.train_policy``
  takes the recorded pairs (``recorded_pairs``: what the observed vehicles' own sensors
  saw, the pairs the prior was fitted on); the std then stays at the pairs' spread (0.38).
* Pairs held back by what the observation does not carry. A driver takes the lowest of its
  constraints; the observation carries the own lane's leader and the limits, not a vehicle
  merging in, a lane change's new leader or a queue beyond the section's end, and those
  only ever lower the acceleration. On SUMO's game/ramp 234 of the 6,008 fitted pairs lie
  more than 1 m/s^2 below the prior (2.6 on average), all but 10 at or upstream of the
  merge, a quarter changing lanes; a Gaussian likelihood took them for drivers' choices
  and held the residual at -0.07 to -0.18 m/s^2 in every regime, queues included. ``policy.residual_pairs`` leaves pairs more than
  ``HELD_MARGIN_MPS2`` below the prior out (``held_back``), except on a closed one-lane
  section, where the leader is the only constraint (docs/deploy-log.md, "Residual on untuned
  networks (stop 28)").
* The start. Snapshot episodes and the recorded pairs begin after the warm-up, and the
  anchors keep each pair's leader speed, so a platoon that starts together (own and
  leader's speed low, delta_v near 0) was anchored nowhere: on ring_two_lane, whose fleet
  departs standing, the trained residual gave -0.15 to -0.24 m/s^2 in the first 20 s, in
  the prior's free regime, and the deployed policies' first minute was 0.8-1.3 m/s slow
  (the prior alone 0.4). Where the truth has a warm-up, the warm-up's states driven by the
  prior (``policy.demand_rollout.warmup_states``) that lie off the pairs are anchors too
  (``warmup_anchor_loss``; docs/deploy-log.md, "ring_two_lane's start (stop 30)").

The policy's form (actor, bound, prior) is unchanged, so checkpoints and the deployment's
numpy twin of ``Agent.mean_action`` are too.
"""

from __future__ import annotations

import torch

from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.road.physics import no_lower_limit_ahead

# The per-feature range of the pairs that counts as covered (quantiles: a handful of
# outlying pairs do not stretch it).
SUPPORT_QUANTILES = (0.005, 0.995)
# Anchor speeds are drawn from 0 to this multiple of the fastest pair's speed.
ANCHOR_SPEED_FACTOR = 1.2
# Spacing at or above which an observation has no leader (road.section.NO_LEADER_GAP_M):
# its delta_v is 0 whatever its speed.
NO_LEADER_SPACING_M = 250.0
# A leader this far away changes no prior's acceleration; a leader that changes it by less
# than FREE_TOL_MPS2 leaves the vehicle in the free regime.
FAR_SPACING_M = 1.0e5
FREE_TOL_MPS2 = 0.05
# How many pairs' weight one anchor has. Weighing one pair, the residual fitted behind
# leaders still leaked into the free regime: free-road speeds up to 2.6 m/s below the
# prior's (netgen_corridor, 59-64% speed within 5% over PPO seeds 1-3); at 10, within
# 0.3 m/s (docs/deploy-log.md, "Why two trainings of the residual differed").
ANCHOR_WEIGHT = 10.0
# A pair whose acceleration falls this far below the prior's is held back by something the
# observation does not carry (``held_back``). On game/ramp's fitted pairs (acc - prior)
# runs from -0.77 (5th percentile) to +0.60 m/s^2 (95th), the lowest 2% beyond -2.3; 3.9%
# lie beyond -1 (docs/deploy-log.md, "Residual on untuned networks (stop 28)").
HELD_MARGIN_MPS2 = 1.0


def pair_support(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-feature (low, high) of the pairs' observations (N, D), raw units."""
    q = torch.tensor(SUPPORT_QUANTILES, dtype=obs.dtype)
    lo, hi = torch.quantile(obs, q, dim=0)
    return lo, hi


def support_weight(
    obs: torch.Tensor, support: tuple[torch.Tensor, torch.Tensor], scale: torch.Tensor
) -> torch.Tensor:
    """(...,) in [0, 1]: 0 inside the support, rising linearly to 1 at one normalisation
    std (``scale``) outside it in the furthest feature. The features are ``scale``'s; a tau
    column after them (``policy.driver_follow``) is no feature of the support."""
    d = scale.shape[-1]
    lo, hi, obs = support[0][..., :d], support[1][..., :d], obs[..., :d]
    outside = torch.clamp(torch.maximum(lo - obs, obs - hi), min=0.0) / scale
    return torch.clamp(outside.amax(dim=-1), max=1.0)


def free_regime(agent: Agent, obs: torch.Tensor) -> torch.Tensor:
    """(...,) bool: where the prior drives as on an empty road (its acceleration within
    ``FREE_TOL_MPS2`` of the one without a leader): the own desired speed sets the
    acceleration there, which the observation does not carry. Under the IDM prior, with a
    look-ahead, also no lower limit ahead: IDM was fitted without those pairs
    (``road.physics.no_lower_limit_ahead``: it cannot see the braking for it, which
    the observation can), so they are the residual's. On the paper's ring that braking was
    40% of the pairs and every pair was otherwise free; fitted nowhere, the residual was
    shaped by the policy gradient alone, its own way per PPO seed (docs/design.md,
    "Leader-follower across PPO seeds")."""
    alone = obs.clone()
    alone[..., 2] = FAR_SPACING_M
    alone[..., 3] = 0.0
    with torch.no_grad():
        free = (agent.prior_accel(obs) - agent.prior_accel(alone)).abs() < FREE_TOL_MPS2
    if agent.prior == "idm":
        free = free & no_lower_limit_ahead(obs)
    return free


def held_back(agent: Agent, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    """(...,) bool: pairs whose action [m/s^2] is more than ``HELD_MARGIN_MPS2`` below the
    prior's: held back by a constraint the observation does not carry, not the driver's
    choice (``residual_pairs``)."""
    with torch.no_grad():
        return act < agent.prior_accel(obs) - HELD_MARGIN_MPS2


def drops_held_pairs(setting: str, closed: bool, max_lanes: int) -> bool:
    """Whether ``policy.residual_pairs`` leaves ``held_back`` pairs out: "driver" yes, "all"
    no, "auto" except on a closed one-lane section, where the leader the observation
    carries is the only constraint (the paper's ring: 82 of its 7,972 fitted pairs brake
    that much harder than the IDM prior, heterogeneous drivers' own choices)."""
    if setting == "auto":
        return not (closed and max_lanes <= 1)
    return setting == "driver"


def residual_pairs(
    agent: Agent, obs: torch.Tensor, act: torch.Tensor, drop_held: bool = False
) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor, torch.Tensor]:
    """The likelihood's pairs' support (``pair_support``, all pairs) and the pairs the
    residual is fitted on: those outside the prior's ``free_regime``, and with
    ``drop_held`` not ``held_back``."""
    keep = ~free_regime(agent, obs)
    if drop_held:
        keep = keep & ~held_back(agent, obs, act)
    return pair_support(obs), obs[keep], act[keep]


def anchor_observations(obs: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """The pairs' observations (N, D) with the own speed (feature 0) redrawn uniformly from
    0 to ``ANCHOR_SPEED_FACTOR`` x the fastest; delta_v (feature 3) moves with it where
    there is a leader, so the leader's speed is kept."""
    v_max = float(obs[:, 0].max()) * ANCHOR_SPEED_FACTOR if len(obs) else 0.0
    v = torch.rand(len(obs), generator=gen, dtype=obs.dtype) * v_max
    out = obs.clone()
    out[:, 0] = v
    has_leader = obs[:, 2] < NO_LEADER_SPACING_M
    out[:, 3] = torch.where(has_leader, obs[:, 3] + (v - obs[:, 0]), obs[:, 3])
    return out


def anchor_loss(
    agent: Agent, anchors: torch.Tensor, support: tuple[torch.Tensor, torch.Tensor]
) -> torch.Tensor:
    """Negative log-likelihood per anchor of pseudo-pairs whose action is the prior's,
    weighted by ``support_weight`` (1 in the prior's ``free_regime``): mean(w r^2) /
    (2 std^2), r the residual, times ``ANCHOR_WEIGHT``: the data's noise, so one anchor
    outside the support counts as ANCHOR_WEIGHT pairs."""
    w = torch.maximum(
        support_weight(anchors, support, agent.scale), free_regime(agent, anchors).to(anchors.dtype)
    )
    return _pseudo_pair_loss(agent, anchors, w)


def _pseudo_pair_loss(agent: Agent, states: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """ANCHOR_WEIGHT x mean(w r^2) / (2 std^2): pairs at ``states`` whose action is the
    prior's, r the residual there, weighted by ``w``."""
    std = agent.log_std.detach().exp()
    return ANCHOR_WEIGHT * (w * agent.residual(states) ** 2).mean() / (2.0 * std**2).squeeze()


def off_support(
    states: torch.Tensor, support: tuple[torch.Tensor, torch.Tensor], scale: torch.Tensor
) -> torch.Tensor:
    """The rows of ``states`` (N, D) outside the pairs' support (``support_weight`` > 0)."""
    return states[support_weight(states, support, scale) > 0.0]


def warmup_anchor_loss(
    agent: Agent, states: torch.Tensor, support: tuple[torch.Tensor, torch.Tensor]
) -> torch.Tensor:
    """``anchor_loss`` for states of the warm-up (``policy.demand_rollout.warmup_states``):
    pseudo-pairs whose action is the prior's, weighted by ``support_weight`` alone. Inside
    the support the pairs and the anchors drawn from them set the residual; the warm-up
    adds the states they do not reach (a standing start)."""
    return _pseudo_pair_loss(agent, states, support_weight(states, support, agent.scale))

"""Stage I on a road section: the generator's features, network, proposal and losses.

The scene and its gaps are ``section_scene``'s; the method is the ring's (Algorithms 2
and 3 of the paper):

* Proposal. One MLP scores every gap of every lane from scale-free, label-free features
  (gap / psi's mean spacing, neighbours' speeds relative to psi's mean speed, the lane's
  limit, its relative index, whether the gap is an open end, how full the lane already is)
  plus global ones: a categorical over all gaps picks where the next vehicle goes, a
  logit-normal its place in the part of the gap that keeps the spacing >= psi's
  spacing_min (plus a longer leader's extra length) to both neighbours, a logit-normal on
  [speed_min, speed_max] its speed, aimed at psi's mean within the speeds that keep it
  reachable, with a sum-constrained draw's spread (``propose``): the completed mean is
  psi's. The place is feasible by construction (the ring's ``truncate``): one law.
* Training. The completed scene is scored with the paper's macro terms, per snapshot:
  L_speed = (mean speed / psi mean speed - 1)^2 over all vehicles, and the spacing terms
  over the front-to-front spacings of every vehicle to its leader in its lane:
  L_mean = (mean / psi mean spacing - 1)^2, L_min = mean of (relu(spacing_min - s) /
  spacing_min)^2, and L_var per ``generator.spacing_dispersion`` (``data.objective``):
  measured (the default) = |mean (s - psi mean spacing)^2 - psi std_spacing_m^2| / psi mean
  spacing^2 where psi has a finite spacing std, the paper's std / psi mean spacing where it
  has none or with ``paper``. On an open section the first vehicle of a lane has no
  leader on the section: its spacing is unknown and left out.
  L_vstd = |std of speeds - target| / psi mean speed (weighted with L_speed by lambda_v)
  where a speed spread is known (``speed_spread_target``: psi's, else the observed
  vehicles'). Positions and speeds are reparameterised; the gap choices get the
  score-function gradient with a batch-mean baseline, as on the ring. ``section_rollout``'s
  ``Scene`` holds the scenes being completed (its training ``rollout``, Algorithm 3 in
  ``section_sampler``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from macromicro_sumo.data.objective import MacroTarget, macro_terms
from macromicro_sumo.generator.posterior import spacing_posterior
from macromicro_sumo.generator.section_bounds import touched_gaps
from macromicro_sumo.generator.section_scene import (
    Gaps,
    Psi,
    Road,
    dispersion_budget,
    lane_exists_share,
    lane_order,
    scene_gaps,
)

FEATURE_VERSION = 2
N_GAP_FEATURES = 11
N_GLOBAL_FEATURES = 10
FRAC_LOG_STD = (-5.0, 2.0)  # limits of the position head's log-std
SPEED_LOG_STD = (-6.0, 1.0)  # limits of the speed head's log-std


# --------------------------------------------------------------------------- features


@dataclass
class Observation:
    """What one autoregressive step sees."""

    gaps: Gaps
    share: torch.Tensor  # (B, G) lane_exists_share
    choosable: torch.Tensor  # (B, G) gaps the next vehicle may go to
    gap_feat: torch.Tensor  # (B, G, N_GAP_FEATURES)
    glob: torch.Tensor  # (B, N_GLOBAL_FEATURES)
    need_v: torch.Tensor  # (B,) mean speed the vehicles still to place need [m/s]
    remaining: torch.Tensor  # (B,) vehicles still to place, the next one included
    budget: torch.Tensor  # (B, G) ``dispersion_budget`` (read with generator.dispersion_feature)


def observe(
    lane: torch.Tensor,
    arc: torch.Tensor,
    speed: torch.Tensor,
    present: torch.Tensor,
    remaining: torch.Tensor,
    total: torch.Tensor,
    psi: Psi,
    road: Road,
    anchor: torch.Tensor,
    extra: torch.Tensor | None = None,
    new_extra: float = 0.0,
) -> Observation:
    """Gaps and scale-free features of the scenes; ``remaining`` counts the vehicles still to
    place (the next one included), ``total`` the vehicles of the completed scene."""
    gaps = scene_gaps(lane, arc, speed, present, road, psi.s_min, anchor, extra, new_extra)
    share = lane_exists_share(gaps, road)
    room_ok = gaps.valid & (gaps.room > 0) & (share > 0)
    # None with room: the section is fuller than psi's minimum spacing allows; every
    # valid gap stays choosable and the placement ends in a (counted) projection.
    choosable = room_ok | (gaps.valid & ~room_ok.any(dim=1, keepdim=True))
    vm, dm, vs = psi.v_mean[:, None], psi.d_mean[:, None], psi.v_scale[:, None]
    # Speeds enter the features detached (as on the ring): a speed reaches the loss only
    # through L_speed, not as a side channel steering later placements.
    v_f, v_l = gaps.v_f.detach(), gaps.v_l.detach()
    usable = share * gaps.room.clamp(min=0.0)
    mid = gaps.start + 0.5 * gaps.length
    limit = road.limit(gaps.lane, mid)
    lane_rel = road.lane_rel[gaps.lane]
    pos_rel = torch.zeros_like(mid) if road.closed else mid.detach() / road.length_m
    gap_feat = torch.stack(
        [
            # lengths as usable on the gap's lane: an empty lane that exists on one short
            # edge is a short gap, not one of the section's length
            (gaps.length - gaps.room.clamp(min=0.0) + usable) / dm,
            torch.where(gaps.room > 0, usable, gaps.room.clamp(min=-dm)) / dm,
            gaps.has_f.double(),
            gaps.has_l.double(),
            torch.where(gaps.has_f, (v_f - vm) / vs, 0.0),
            torch.where(gaps.has_l, (v_l - vm) / vs, 0.0),
            ((limit - vm) / vs).clamp(-10.0, 10.0),
            lane_rel,
            share,
            gaps.n_lane * dm / road.lane_extent_m[gaps.lane],
            pos_rel,
        ],
        dim=-1,
    )
    n_present = present.sum(dim=1).double()
    v_sum = (speed * present).sum(dim=1)
    rem = remaining.double().clamp(min=1.0)
    need_v = (total * psi.v_mean - v_sum) / rem
    need_in = (total * psi.v_mean - v_sum.detach()) / rem
    mean_v = torch.where(n_present > 0, v_sum.detach() / n_present.clamp(min=1), psi.v_mean)
    tot = total.double().clamp(min=1.0)
    glob = torch.stack(
        [
            remaining.double() / tot,
            n_present / tot,
            ((need_in - psi.v_mean) / psi.v_scale).clamp(-10.0, 10.0),
            (mean_v - psi.v_mean) / psi.v_scale,
            psi.s_min / psi.d_mean,
            psi.d_std / psi.d_mean,
            psi.d_std_known.double(),
            (psi.v_max - psi.v_min) / psi.v_mean,
            torch.full_like(rem, float(road.closed)),
            tot * psi.d_mean / road.lane_length_m,
        ],
        dim=-1,
    )
    budget = dispersion_budget(gaps, total, psi, road)
    return Observation(gaps, share, choosable, gap_feat, glob, need_v, remaining, budget)


# --------------------------------------------------------------------------- model


class SectionGeneratorNet(nn.Module):
    """ReLU MLP scoring every gap: (choice logit, position mean, position log-std, speed
    residual, speed log-std).

    One hidden layer by default (``hidden_layers``: two, the ring generator's depth): the
    net runs once per gap per placed vehicle (a 1,000-snapshot completion evaluates it ~10^7
    times), and the global features enter once per scene;
    ReLU rather than the ring's tanh for the same reason (tanh was half of inference time).
    """

    def __init__(
        self,
        hidden_size: int = 64,
        gap_choice: str = "network",
        dispersion_feature: bool = False,
        hidden_layers: int = 1,
    ) -> None:
        super().__init__()
        self.hidden_size = hidden_size
        # ``generator.hidden_layers``: a second ReLU layer (the ring's depth) where 2; with 1
        # the network and its initial weights are as before the key existed.
        self.hidden_layers = hidden_layers
        # ``generator.dispersion_feature``: each gap also sees ``dispersion_budget`` (one
        # more input; off, the network and its initial weights are as before it existed).
        self.dispersion_feature = dispersion_feature
        # How a rollout picks the next vehicle's gap (``generator.gap_choice``): "network"
        # from the choice logits, "posterior" from ``posterior_log_probs`` (closed one-lane
        # sections; the logits are then unused where psi has a spacing std).
        self.gap_choice = gap_choice
        self.gap_in = nn.Linear(N_GAP_FEATURES + int(dispersion_feature), hidden_size, bias=False)
        self.glob_in = nn.Linear(N_GLOBAL_FEATURES, hidden_size)
        deep = [(nn.Linear(hidden_size, hidden_size), nn.ReLU()) for _ in range(hidden_layers - 1)]
        self.deep = nn.Sequential(*(m for pair in deep for m in pair))  # empty: the identity
        self.head = nn.Linear(hidden_size, 5)

    def forward(
        self, gap_feat: torch.Tensor, glob: torch.Tensor, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, G, 5) outputs; with ``mask`` (B, G) only those gaps are evaluated (the rest
        read 0): most slots of a scene being completed are still empty."""
        g = self.glob_in(glob.float())
        if mask is None:
            return self.head(
                self.deep(torch.relu(self.gap_in(gap_feat.float()) + g[:, None, :]))
            ).double()
        rows, cols = mask.nonzero(as_tuple=True)
        h = torch.relu(self.gap_in(gap_feat[rows, cols].float()) + g[rows])
        out = torch.zeros(*mask.shape, 5, dtype=torch.float64)
        return out.index_put((rows, cols), self.head(self.deep(h)).double())


def speed_range(
    need_v: torch.Tensor, remaining: torch.Tensor, psi: Psi
) -> tuple[torch.Tensor, ...]:
    """Speeds [lo, hi] for the next vehicle that keep psi's mean reachable: the r - 1 after
    it can still average what is left within [v_min, v_max] (exact look-ahead for the mean,
    as the ring's is for gaps). The last vehicle's range is the one speed it needs. Where
    psi's mean is out of reach from the start, the whole of [v_min, v_max]."""
    r = remaining.double().clamp(min=1.0)
    lo = torch.maximum(psi.v_min, r * need_v - (r - 1.0) * psi.v_max)
    hi = torch.minimum(psi.v_max, r * need_v - (r - 1.0) * psi.v_min)
    bad = lo > hi
    return torch.where(bad, psi.v_min, lo), torch.where(bad, psi.v_max, hi)


def _speed_base(need_v: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Logit of the speed the remaining vehicles need, on [lo, hi]: the speed head adds a
    residual, so an untrained net already aims at psi's mean speed."""
    u = ((need_v - lo) / (hi - lo).clamp(min=1e-6)).clamp(1e-4, 1.0 - 1e-4)
    return torch.logit(u)


@dataclass
class Trials:
    """``n`` candidates for the next vehicle of each of B scenes, (B, n) each."""

    choice: torch.Tensor
    lane: torch.Tensor
    arc: torch.Tensor
    speed: torch.Tensor
    log_p: torch.Tensor  # log-probability of the gap choice
    probs: torch.Tensor  # (B, G) the gap choice's distribution (detached)


def gap_input(net: SectionGeneratorNet, obs: Observation) -> torch.Tensor:
    """(B, G, inputs) what the network reads of each gap: its features, and with
    ``dispersion_feature`` its ``dispersion_budget`` after them."""
    if not net.dispersion_feature:
        return obs.gap_feat
    return torch.cat([obs.gap_feat, obs.budget[..., None]], dim=-1)


def propose(
    net: SectionGeneratorNet, obs: Observation, psi: Psi, road: Road, n: int, gen: torch.Generator
) -> Trials:
    """Sample ``n`` candidates per scene: a gap, a point in its admissible part, a speed."""
    out = net(gap_input(net, obs), obs.glob, obs.gaps.valid)  # (B, G, 5)
    b = out.shape[0]
    logits = out[..., 0]
    if net.gap_choice == "posterior":
        post, known = posterior_log_probs(obs, psi)
        logits = torch.where(known[:, None], post, logits)
    logits = logits.masked_fill(~obs.choosable, -math.inf)
    log_p = torch.log_softmax(logits, dim=1)
    choice = torch.multinomial(log_p.detach().exp(), n, replacement=True, generator=gen)
    pick = out.gather(1, choice[..., None].expand(-1, -1, out.shape[-1]))  # (B, n, 5)
    eps = torch.randn(b, n, 2, generator=gen, dtype=torch.float64)
    g = obs.gaps
    frac = torch.sigmoid(pick[..., 1] + pick[..., 2].clamp(*FRAC_LOG_STD).exp() * eps[..., 0])
    frac = frac.clamp(1e-6, 1.0 - 1e-6)
    lane = g.lane.gather(1, choice)
    a = g.start.gather(1, choice) + g.lo.gather(1, choice)
    arc = road.wrap(road.place_on_lane(lane, a, g.room.gather(1, choice).clamp(min=0.0), frac))
    # Bridge: of r vehicles still to place whose speeds must average need_v, the next one
    # given that constraint deviates by sqrt((r - 1) / r) of the unconstrained spread (the
    # conditional law of exchangeable draws given their sum); the last one takes need_v.
    # Without it the last vehicle's own spread stays in the completed mean (measured on
    # the Bremen section: 0.11 m/s held-out error, last vehicles 10-18 m/s off psi). The
    # range keeps the speed the last one needs within psi's bounds (``speed_range``).
    r = obs.remaining.double().clamp(min=1.0)
    bridge = torch.sqrt((r - 1.0) / r)[:, None]
    v_lo, v_hi = speed_range(obs.need_v, obs.remaining, psi)
    u = torch.sigmoid(
        _speed_base(obs.need_v, v_lo, v_hi)[:, None]
        + bridge * (pick[..., 3] + pick[..., 4].clamp(*SPEED_LOG_STD).exp() * eps[..., 1])
    )
    speed = v_lo[:, None] + (v_hi - v_lo)[:, None] * u
    probs = log_p.detach().exp()
    return Trials(choice, lane, arc, speed, log_p.gather(1, choice), probs)


def posterior_log_probs(obs: Observation, psi: Psi) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, G) log-probability that the next vehicle goes into each gap under i.i.d. normal
    spacings with psi's mean and std (``posterior.spacing_posterior``, the ring's
    ``gap_choice = "posterior"``), and (B,) whether psi has a spacing std to use.

    One lane of a closed section is the ring: every gap is a spacing between two vehicles
    (or the whole loop when none is placed yet). The valid gaps are packed to the front of
    each row, as the ring's function wants them. A row whose posterior leaves no mass on a
    choosable gap (all of it on gaps without room) takes every choosable gap alike.
    """
    g = obs.gaps
    valid = g.valid.numpy()
    rows = np.arange(len(valid))[:, None]
    order = np.argsort(~valid, axis=1, kind="stable")
    d_std = psi.d_std.numpy()
    known = psi.d_std_known.numpy() & (d_std > 0)
    packed = spacing_posterior(
        g.length.detach().numpy()[rows, order],
        valid[rows, order],
        obs.remaining.numpy(),
        psi.d_mean.numpy(),
        np.where(known, d_std, 1.0),
    )
    post = np.empty_like(packed)
    post[rows, order] = packed
    lp = torch.as_tensor(post)
    none = ~torch.isfinite(lp.masked_fill(~obs.choosable, -math.inf)).any(dim=1, keepdim=True)
    return torch.where(none, 0.0, lp), torch.as_tensor(known)


# --------------------------------------------------------------------------- losses


def spacings(
    lane: torch.Tensor,
    arc: torch.Tensor,
    present: torch.Tensor,
    road: Road,
    generated_from: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, M) front-to-front spacing of each vehicle to its leader in its lane, and whether
    it counts (not for a lane's first vehicle on an open section: unknown); with
    ``generated_from`` (the first generated slot), only the ring's A (``touched_gaps``)."""
    lo_ = lane_order(lane, arc, present, road)
    counts = lo_["has_l"] & lo_["present"]
    if generated_from is not None:
        counts = counts & touched_gaps(lo_, generated_from, road)
    return lo_["lead_arc"] - lo_["arc"], counts


def section_losses(
    lane: torch.Tensor,
    arc: torch.Tensor,
    speed: torch.Tensor,
    present: torch.Tensor,
    psi: Psi,
    road: Road,
    dispersion: str = "measured",
    center: str = "psi",
    generated_from: int | None = None,
) -> dict[str, torch.Tensor]:
    """The macro terms of completed scenes, (B,) each (``data.objective``): every present
    vehicle's speed, and every per-lane spacing on the section as A (L_max is 0 where
    psi has no upper spacing bound). ``dispersion``: ``generator.spacing_dispersion``;
    ``center``: ``generator.dispersion_center``; ``generated_from`` (the first generated
    slot): A holds only the spacings a generated vehicle touches
    (``generator.spacing_set = "touched"``)."""
    sp, has = spacings(lane, arc, present, road)
    in_a = has if generated_from is None else spacings(lane, arc, present, road, generated_from)[1]
    scene_mean = None
    if center == "scene" and road.closed:
        # Around a loop A is every spacing of the scene: their mean is exact (the lane
        # loops' lengths over the vehicles), where psi's is an estimate (the paper's ring
        # as a section, before E2 counted a vehicle once: 117.8 m for 125.7 m, and the
        # spread around the wrong mean read 60 m^2 too wide, the scenes ~4% too narrow).
        w = has.double()
        scene_mean = ((sp * w).sum(dim=1) / w.sum(dim=1).clamp(min=1.0)).detach()
    # the touched A is part of the loop: its mean is judged against the loop's exact one
    d_target = scene_mean if scene_mean is not None and generated_from is not None else psi.d_mean
    target = MacroTarget(
        psi.v_mean,
        d_target,
        psi.d_min,
        psi.d_max,
        spacing_std_m=(
            torch.where(psi.d_std_known, psi.d_std, math.nan) if dispersion == "measured" else None
        ),
        speed_std_mps=psi.v_std,
        spacing_center_m=scene_mean,
    )
    # eps under the square roots keeps equal spacings and speeds trainable.
    return macro_terms(speed, present.double(), sp, in_a.double(), target, eps=1e-8)

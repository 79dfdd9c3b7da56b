"""Stage I on a road section: complete the hidden vehicles of a snapshot (lanes, open ends).

The ring generator (``generator.py``) places K hidden vehicles in the gaps of one lane
loop. Here the scene is a section of a user's network: several lanes, lane counts that
change from edge to edge, an open corridor (vehicles enter upstream and leave downstream)
or a closed loop, and a hidden count K that varies per snapshot (estimated from the
detectors' density). The method is the same (Algorithms 2 and 3 of the paper):

* Gaps. Every lane is cut by its vehicles into gaps: between consecutive vehicles, and on
  an open section the two open ends (upstream of the lane's last vehicle, downstream of its
  first); on a closed section the last gap wraps around the loop. An empty lane is one gap
  of the section's length (closed: from a random anchor, the loop has no start).
* Proposal. One MLP scores every gap of every lane from scale-free, label-free features
  (gap / psi's mean spacing, neighbours' speeds relative to psi's mean speed, the lane's
  limit, its relative index, whether the gap is an open end, how full the lane already is)
  plus global ones: a categorical over all gaps picks where the next vehicle goes, a
  logit-normal picks its place inside the part of the gap that keeps the front-to-front
  spacing >= psi's spacing_min to both neighbours, a logit-normal on psi's
  [speed_min, speed_max] its speed, centred on the speed the vehicles still to place need
  for psi's mean and restricted to the speeds that keep that mean reachable, with the
  spread of a sum-constrained draw (``propose``): the completed mean equals psi's. The place is thus feasible for spacing by construction, the
  ``truncate`` limit of the ring generator, so training and inference sample the same law.
* Rejection (Algorithm 3). Each vehicle gets up to T_max trials; a trial fails if its
  position lies on an edge that lacks the gap's lane (a lane drop inside the gap) or
  breaks a bound; after T_max failures the last trial is projected onto the nearest
  feasible point (of its gap, else of the most likely gap that has one) and counted.
  Gaps with no room at all (a gap shorter than two minimum spacings) are not chosen
  unless no gap has room (the section is fuller than psi allows: projection, counted).
* Training. The completed scene is scored with the paper's macro terms, per snapshot:
  L_speed = (mean speed / psi mean speed - 1)^2 over all vehicles, and the spacing terms
  over the front-to-front spacings of every vehicle to its leader in its lane:
  L_mean = (mean / psi mean spacing - 1)^2, L_min = mean of (relu(spacing_min - s) /
  spacing_min)^2, L_var = |std - psi std_spacing_m| / psi mean spacing where psi has a
  finite spacing std (zero where the detectors cannot tell). On an open section the
  first vehicle of a lane has no leader on the section: its spacing is unknown and left
  out (``section.lane_leaders`` reports NO_LEADER_GAP_M for it, not a measurement).
  L_vstd = |std of speeds - target| / psi mean speed (weighted with L_speed by lambda_v)
  where a speed spread is known (``speed_spread_target``: psi's, else the observed
  vehicles'). Positions and speeds are reparameterised; the gap choices get the score-function
  gradient with a batch-mean baseline, as on the ring.

Geometry and features are torch (float64 for positions), one definition for the training
rollout (with gradients) and for inference (no_grad, T_max trials per step at once,
batched over snapshots).
"""

from __future__ import annotations

import contextlib
import copy
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import nn

from macromicro_sumo.checkpoints import load_network, save_network
from macromicro_sumo.data.objective import MacroTarget, macro_loss, macro_terms
from macromicro_sumo.data.ring import split_runs
from macromicro_sumo.data.section import PSI_FIELDS, SectionSnapshots, section_snapshots
from macromicro_sumo.files import prepare_out_dir, write_csv, write_json
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.section import Section, lane_leaders
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.truth.section import load_section_truth

FEATURE_VERSION = 2
CHECKPOINT_FORMAT = "macromicro-section-generator"
N_GAP_FEATURES = 11
N_GLOBAL_FEATURES = 10
LOSS_TERMS = ("L_speed", "L_vstd", "L_mean", "L_min", "L_var")
FRAC_LOG_STD = (-5.0, 2.0)  # limits of the position head's log-std
SPEED_LOG_STD = (-6.0, 1.0)  # limits of the speed head's log-std
END_MARGIN_M = 1e-6  # keeps a vehicle at an open downstream end strictly on the section
LANE_PROBES = 8  # points per gap that estimate the share of it where its lane exists
TOL_M = 1e-6  # rounding allowed in the spacing check [m]
EVAL_BATCH = 256  # snapshots per forward pass in validation and metrics

_PSI = {name: i for i, name in enumerate(PSI_FIELDS)}


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Run torch on one thread inside the block: the per-step arrays are small, and on a
    shared machine torch's thread pool made completion ten times slower (measured)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# --------------------------------------------------------------------------- road and psi


@dataclass(frozen=True)
class Road:
    """What the generator needs of a ``Section``, as torch tensors (positions in float64)."""

    length_m: float
    closed: bool
    max_lanes: int
    lane_length_m: float
    offsets_m: torch.Tensor  # (E,)
    n_lanes: torch.Tensor  # (E,) int64
    limits_mps: torch.Tensor  # (E, max lanes); a lane the edge lacks has its leftmost's limit
    # per lane index: (a, b) arc intervals where that lane exists (numpy, for projection)
    lane_spans: tuple[np.ndarray, ...]
    # the same as one (lanes, P, 2) tensor, padded with empty spans; on a loop repeated
    # one and two lengths on, since a gap may run past the loop's end
    span_table: torch.Tensor
    lane_extent_m: torch.Tensor  # (lanes,) arc length on which each lane index exists

    @classmethod
    def of(cls, section: Section) -> Road:
        lim = np.array(section.limits_mps, dtype=np.float64)
        n_lanes = np.asarray(section.n_lanes, dtype=np.int64)
        for e, n in enumerate(n_lanes):
            lim[e, n:] = lim[e, n - 1]
        ends = np.append(section.offsets_m[1:], section.length_m)
        spans = []
        for lane in range(section.max_lanes):
            has = n_lanes > lane
            pieces: list[list[float]] = []
            for e in np.flatnonzero(has):
                a, b = float(section.offsets_m[e]), float(ends[e])
                if pieces and abs(pieces[-1][1] - a) < 1e-9:
                    pieces[-1][1] = b
                else:
                    pieces.append([a, b])
            spans.append(np.array(pieces, dtype=np.float64).reshape(-1, 2))
        reps = 3 if section.closed else 1
        p = max(len(x) for x in spans) * reps
        table = np.zeros((section.max_lanes, p, 2))
        for lane, x in enumerate(spans):
            rep = np.concatenate([x + k * section.length_m for k in range(reps)])
            table[lane, : len(rep)] = rep
        return cls(
            length_m=section.length_m,
            closed=section.closed,
            max_lanes=section.max_lanes,
            lane_length_m=section.lane_length_m,
            offsets_m=torch.as_tensor(np.asarray(section.offsets_m, dtype=np.float64)),
            n_lanes=torch.as_tensor(n_lanes),
            limits_mps=torch.as_tensor(lim),
            lane_spans=tuple(spans),
            lane_extent_m=torch.as_tensor([float(np.sum(x[:, 1] - x[:, 0])) for x in spans]),
            span_table=torch.as_tensor(table),
        )

    def wrap(self, arc: torch.Tensor) -> torch.Tensor:
        return torch.remainder(arc, self.length_m) if self.closed else arc

    def edge(self, arc: torch.Tensor) -> torch.Tensor:
        """Edge index (the junction after an edge counts as that edge) of each position."""
        e = torch.bucketize(self.wrap(arc.detach()).contiguous(), self.offsets_m, right=True) - 1
        return e.clamp(0, len(self.offsets_m) - 1)

    def has_lane(self, lane: torch.Tensor, arc: torch.Tensor) -> torch.Tensor:
        """Whether the edge at ``arc`` has lane index ``lane`` (same shapes)."""
        return self.n_lanes[self.edge(arc)] > lane

    def limit(self, lane: torch.Tensor, arc: torch.Tensor) -> torch.Tensor:
        """Speed limit [m/s] of lane ``lane`` at ``arc`` (the edge's leftmost where it lacks it)."""
        e = self.edge(arc)
        return self.limits_mps[e, lane.clamp(0, self.max_lanes - 1)]

    def place_on_lane(
        self, lane: torch.Tensor, a: torch.Tensor, room: torch.Tensor, frac: torch.Tensor
    ) -> torch.Tensor:
        """The point at share ``frac`` of the length of [a, a + room] on which ``lane``
        exists (the pieces laid end to end): a gap across a lane drop only offers the
        part where its lane is. Where the lane is nowhere in it, ``a + frac room``."""
        spans = self.span_table[lane]  # (..., P, 2)
        pa = torch.maximum(a[..., None], spans[..., 0])
        plen = (torch.minimum((a + room)[..., None], spans[..., 1]) - pa).clamp(min=0.0)
        cum = plen.cumsum(dim=-1)
        total = cum[..., -1]
        t = frac * total
        piece = (t.detach()[..., None] >= cum.detach()).sum(dim=-1, keepdim=True)
        piece = piece.clamp(max=spans.shape[-2] - 1)
        x = pa.gather(-1, piece) + (t[..., None] - (cum - plen).gather(-1, piece))
        return torch.where(total > 0, x[..., 0], a + frac * room)

    def nearest_on_lane(self, lane: int, a: float, b: float, x: float) -> float | None:
        """The point of [a, b] nearest to ``x`` where lane ``lane`` exists (None: nowhere)."""
        if b < a:
            return None
        spans = self.lane_spans[lane]
        if self.closed:  # [a, b] may run past the loop's end (a < 2 L, b < 3 L)
            spans = np.concatenate([spans + k * self.length_m for k in range(3)])
        lo = np.maximum(spans[:, 0], a)
        hi = np.minimum(spans[:, 1] - END_MARGIN_M, b)
        ok = lo <= hi
        if not ok.any():
            return None
        near = np.clip(x, lo[ok], hi[ok])
        return float(near[np.argmin(np.abs(near - x))])


@dataclass(frozen=True)
class Psi:
    """psi of a batch of snapshots as named (B,) float64 tensors."""

    v_mean: torch.Tensor
    d_mean: torch.Tensor
    d_std: torch.Tensor  # 0 where the detectors give no spacing std
    d_std_known: torch.Tensor  # bool
    v_min: torch.Tensor
    v_max: torch.Tensor
    s_min: torch.Tensor

    # speed spread target [m/s] (NaN where unknown; ``speed_spread_target``)
    v_std: torch.Tensor | None = None

    @classmethod
    def of(cls, psi: np.ndarray, v_std: np.ndarray | None = None) -> Psi:
        p = torch.as_tensor(np.asarray(psi, dtype=np.float64))
        d_std = p[:, _PSI["std_spacing_m"]]
        known = torch.isfinite(d_std)
        return cls(
            v_mean=p[:, _PSI["mean_speed_mps"]],
            d_mean=p[:, _PSI["mean_spacing_m"]],
            d_std=torch.where(known, d_std, 0.0),
            d_std_known=known,
            v_min=p[:, _PSI["speed_min_mps"]],
            v_max=p[:, _PSI["speed_max_mps"]],
            s_min=p[:, _PSI["spacing_min_m"]],
            v_std=None if v_std is None else torch.as_tensor(np.asarray(v_std, np.float64)),
        )

    def take(self, idx: torch.Tensor) -> Psi:
        return Psi(
            *(
                None if getattr(self, f) is None else getattr(self, f)[idx]
                for f in self.__dataclass_fields__
            )
        )

    @property
    def v_scale(self) -> torch.Tensor:
        """Half the admissible speed range (at least 0.1 m/s): the unit of speed features."""
        return (0.5 * (self.v_max - self.v_min)).clamp(min=0.1)


# --------------------------------------------------------------------------- scene geometry


@dataclass
class Gaps:
    """Every gap of every lane, (B, G) each: G = M vehicle slots (the gap ahead of each
    vehicle, in (lane, arc) order) + one head gap per lane (open section: upstream of the
    lane's last vehicle, the whole lane when empty; closed: the whole loop of an empty lane).

    A new vehicle at ``start + a`` keeps both spacings >= s_min iff lo <= a <= hi.
    """

    start: torch.Tensor
    length: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    lane: torch.Tensor
    has_f: torch.Tensor  # a vehicle behind (False: the open upstream end, or an empty lane)
    has_l: torch.Tensor  # a vehicle ahead (False: the open downstream end, or an empty lane)
    v_f: torch.Tensor  # speed of the vehicle behind (0 where none)
    v_l: torch.Tensor
    valid: torch.Tensor
    n_lane: torch.Tensor  # vehicles already on the gap's lane

    @property
    def room(self) -> torch.Tensor:
        return self.hi - self.lo


def lane_order(
    lane: torch.Tensor, arc: torch.Tensor, present: torch.Tensor, road: Road
) -> dict[str, torch.Tensor]:
    """Vehicles sorted by (lane, arc), each with its leader in the lane, batched (B, M).

    Returns sorted ``lane``, ``arc``, ``present``, ``order`` (slot of each sorted entry),
    ``lead_arc`` (the leader's arc, unwrapped: + L around a loop; the open end L on an
    open section), ``has_l`` (a leader exists), ``has_next`` (the leader is the next entry,
    not around the loop), and per lane ``count``, ``first_slot``, ``first_arc`` (B, lanes).
    """
    b, m = arc.shape
    nl = road.max_lanes
    big = 4.0 * road.length_m
    key = torch.where(present, lane.double() * big + arc.detach(), math.inf)
    order = key.argsort(dim=1)
    s_lane = lane.gather(1, order)
    s_arc = arc.gather(1, order)
    s_pres = present.gather(1, order)
    same = s_pres[:, 1:] & (s_lane[:, 1:] == s_lane[:, :-1])
    has_next = torch.cat([same, same.new_zeros(b, 1)], dim=1)
    onehot = (lane[..., None] == torch.arange(nl)) & present[..., None]  # (B, M, lanes)
    count = onehot.sum(dim=1)
    first_slot = torch.where(onehot, arc.detach()[..., None], math.inf).argmin(dim=1)
    first_arc = arc.gather(1, first_slot)
    lane_c = s_lane.clamp(0, nl - 1)
    next_arc = torch.cat([s_arc[:, 1:], s_arc[:, -1:]], dim=1)
    if road.closed:
        lead_arc = torch.where(has_next, next_arc, first_arc.gather(1, lane_c) + road.length_m)
        has_l = s_pres
    else:
        lead_arc = torch.where(has_next, next_arc, road.length_m)
        has_l = has_next
    return {
        "lane": s_lane,
        "arc": s_arc,
        "present": s_pres,
        "order": order,
        "lead_arc": lead_arc,
        "has_l": has_l,
        "has_next": has_next,
        "count": count,
        "first_slot": first_slot,
        "first_arc": first_arc,
    }


def scene_gaps(
    lane: torch.Tensor,
    arc: torch.Tensor,
    speed: torch.Tensor,
    present: torch.Tensor,
    road: Road,
    s_min: torch.Tensor,
    anchor: torch.Tensor,
) -> Gaps:
    """The gaps of the current scenes (``Gaps``); ``anchor`` (B, lanes) is where an empty
    lane's gap starts on a closed section."""
    b, m = arc.shape
    nl = road.max_lanes
    lo_ = lane_order(lane, arc, present, road)
    s_v = speed.gather(1, lo_["order"])
    lane_c = lo_["lane"].clamp(0, nl - 1)
    first_v = speed.gather(1, lo_["first_slot"])
    next_v = torch.cat([s_v[:, 1:], s_v[:, -1:]], dim=1)
    if road.closed:
        v_l = torch.where(lo_["has_next"], next_v, first_v.gather(1, lane_c))
    else:
        v_l = torch.where(lo_["has_next"], next_v, 0.0)
    has_l = lo_["has_l"]
    length = lo_["lead_arc"] - lo_["arc"]
    s_min_c = s_min[:, None]
    lo = s_min_c.expand(b, m)
    hi = length - torch.where(has_l, s_min_c, END_MARGIN_M)
    count = lo_["count"]
    occupied = count > 0
    lanes = torch.arange(nl).expand(b, nl)
    if road.closed:
        h_start = anchor
        h_len = torch.full((b, nl), road.length_m, dtype=torch.float64)
        h_hi = h_len - END_MARGIN_M
        h_valid = ~occupied
        h_has_l = torch.zeros_like(occupied)
        h_v_l = torch.zeros_like(h_len)
    else:
        first_arc = lo_["first_arc"]
        h_start = torch.zeros(b, nl, dtype=torch.float64)
        h_len = torch.where(occupied, first_arc, road.length_m)
        h_hi = torch.where(occupied, first_arc - s_min_c, road.length_m - END_MARGIN_M)
        h_valid = torch.ones_like(occupied)
        h_has_l = occupied
        h_v_l = torch.where(occupied, first_v, 0.0)
    return Gaps(
        start=torch.cat([lo_["arc"], h_start], dim=1),
        length=torch.cat([length, h_len], dim=1),
        lo=torch.cat([lo, torch.zeros(b, nl, dtype=torch.float64)], dim=1),
        hi=torch.cat([hi, h_hi], dim=1),
        lane=torch.cat([lo_["lane"], lanes], dim=1),
        has_f=torch.cat([lo_["present"], torch.zeros_like(occupied)], dim=1),
        has_l=torch.cat([has_l, h_has_l], dim=1),
        v_f=torch.cat([torch.where(lo_["present"], s_v, 0.0), torch.zeros_like(h_len)], dim=1),
        v_l=torch.cat([torch.where(has_l, v_l, 0.0), h_v_l], dim=1),
        valid=torch.cat([lo_["present"], h_valid], dim=1),
        n_lane=torch.cat([count.gather(1, lane_c), count], dim=1).double(),
    )


def lane_exists_share(gaps: Gaps, road: Road) -> torch.Tensor:
    """(B, G) share of each gap's admissible part [lo, hi] on edges that have its lane
    (exact: the overlap with the lane's spans; 0 for a gap without room)."""
    a = (gaps.start + gaps.lo).detach()
    room = gaps.room.detach()
    spans = road.span_table[gaps.lane]  # (B, G, P, 2)
    over = torch.minimum((a + room)[..., None], spans[..., 1]) - torch.maximum(
        a[..., None], spans[..., 0]
    )
    share = over.clamp(min=0.0).sum(dim=-1) / room.clamp(min=1e-9)
    return torch.where(room > 0, share.clamp(max=1.0), 0.0)


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
) -> Observation:
    """Gaps and scale-free features of the scenes; ``remaining`` counts the vehicles still to
    place (the next one included), ``total`` the vehicles of the completed scene."""
    gaps = scene_gaps(lane, arc, speed, present, road, psi.s_min, anchor)
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
    lane_rel = gaps.lane.double() / max(road.max_lanes - 1, 1)
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
    return Observation(gaps, share, choosable, gap_feat, glob, need_v, remaining)


# --------------------------------------------------------------------------- model


class SectionGeneratorNet(nn.Module):
    """One-hidden-layer ReLU MLP scoring every gap: (choice logit, position mean, position
    log-std, speed residual, speed log-std).

    One hidden layer: the net runs once per gap per placed vehicle (a 1,000-snapshot
    completion evaluates it ~10^7 times), and the global features enter once per scene;
    ReLU rather than the ring's tanh for the same reason (tanh was half of inference time).
    """

    def __init__(self, hidden_size: int = 64) -> None:
        super().__init__()
        self.hidden_size = hidden_size
        self.gap_in = nn.Linear(N_GAP_FEATURES, hidden_size, bias=False)
        self.glob_in = nn.Linear(N_GLOBAL_FEATURES, hidden_size)
        self.head = nn.Linear(hidden_size, 5)

    def forward(
        self, gap_feat: torch.Tensor, glob: torch.Tensor, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, G, 5) outputs; with ``mask`` (B, G) only those gaps are evaluated (the rest
        read 0): most slots of a scene being completed are still empty."""
        g = self.glob_in(glob.float())
        if mask is None:
            return self.head(torch.relu(self.gap_in(gap_feat.float()) + g[:, None, :])).double()
        rows, cols = mask.nonzero(as_tuple=True)
        h = torch.relu(self.gap_in(gap_feat[rows, cols].float()) + g[rows])
        out = torch.zeros(*mask.shape, 5, dtype=torch.float64)
        return out.index_put((rows, cols), self.head(h).double())


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


def propose(
    net: SectionGeneratorNet, obs: Observation, psi: Psi, road: Road, n: int, gen: torch.Generator
) -> Trials:
    """Sample ``n`` candidates per scene: a gap, a point in its admissible part, a speed."""
    out = net(obs.gap_feat, obs.glob, obs.gaps.valid)  # (B, G, 5)
    b = out.shape[0]
    logits = out[..., 0].masked_fill(~obs.choosable, -math.inf)
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


# --------------------------------------------------------------------------- losses


def spacings(
    lane: torch.Tensor, arc: torch.Tensor, present: torch.Tensor, road: Road
) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, M) front-to-front spacing of each vehicle to its leader in its lane, and whether
    it counts: a vehicle with no leader on an open section (the first of its lane) has an
    unknown spacing and is left out."""
    lo_ = lane_order(lane, arc, present, road)
    return lo_["lead_arc"] - lo_["arc"], lo_["has_l"] & lo_["present"]


def section_losses(
    lane: torch.Tensor,
    arc: torch.Tensor,
    speed: torch.Tensor,
    present: torch.Tensor,
    psi: Psi,
    road: Road,
) -> dict[str, torch.Tensor]:
    """The macro terms of completed scenes, (B,) each (``data.objective``): every present
    vehicle's speed, and every per-lane spacing on the section as A (psi has no upper
    spacing bound: L_max is 0)."""
    sp, has = spacings(lane, arc, present, road)
    target = MacroTarget(
        psi.v_mean,
        psi.d_mean,
        psi.s_min,
        torch.full_like(psi.d_mean, math.inf),
        spacing_std_m=torch.where(psi.d_std_known, psi.d_std, math.nan),
        speed_std_mps=psi.v_std,
    )
    # eps under the square roots keeps equal spacings and speeds trainable.
    return macro_terms(speed, present.double(), sp, has.double(), target, eps=1e-8)


MIN_OBSERVED_FOR_SPREAD = 3  # observed vehicles needed to estimate a speed spread


def speed_spread_target(snaps: SectionSnapshots) -> np.ndarray:
    """(S,) the speed std [m/s] the completed scene should have: psi's ``std_speed_mps``
    where psi carries one, else the spread of the observed vehicles' speeds (a sample of
    the same stream; NaN with fewer than MIN_OBSERVED_FOR_SPREAD of them).

    Why: psi's other fields say nothing about the speed spread, and with the mean bridged
    exactly (``propose``) nothing else in the loss does: the spread stayed at the speed
    head's initial value (Bremen: 12.2 m/s completed vs 6.9 m/s true)."""
    if "std_speed_mps" in _PSI:
        return np.asarray(snaps.psi[:, _PSI["std_speed_mps"]], dtype=np.float64)
    obs = snaps.valid & snaps.observed
    n = obs.sum(axis=1)
    v = np.where(obs, snaps.speed_mps, 0.0)
    mean = v.sum(axis=1) / np.maximum(n, 1)
    var = (np.where(obs, snaps.speed_mps - mean[:, None], 0.0) ** 2).sum(axis=1)
    std = np.sqrt(var / np.maximum(n - 1, 1))
    return np.where(n >= MIN_OBSERVED_FOR_SPREAD, std, np.nan)


# --------------------------------------------------------------------------- rollouts


@dataclass
class _Scene:
    """Observed vehicles in the first N slots, the generated ones after (B, N + K_max)."""

    lane: torch.Tensor
    arc: torch.Tensor
    speed: torch.Tensor
    present: torch.Tensor
    n_obs_slots: int
    k: torch.Tensor  # (B,) vehicles to generate
    total: torch.Tensor  # (B,) vehicles of the completed scene

    # (B, n_obs_slots) the snapshot slot of each packed observed slot (-1: none)
    source_slot: np.ndarray | None = None

    @classmethod
    def start(cls, snaps: SectionSnapshots, k: np.ndarray, road: Road) -> _Scene:
        """The observed vehicles packed to the front (a snapshot's hidden slots are never
        present: packing shrinks every per-step array), K_max empty slots after them."""
        obs = np.asarray(snaps.valid & snaps.observed, dtype=bool)
        k_t = torch.as_tensor(np.maximum(np.asarray(k, dtype=np.int64), 0))
        k_max = int(k_t.max()) if len(k_t) else 0
        b = len(obs)
        n = max(int(obs.sum(axis=1).max()) if b else 0, 1)
        slot = np.argsort(~obs, axis=1, kind="stable")[:, :n]
        rows = np.arange(b)[:, None]
        packed = obs[rows, slot]
        source = np.where(packed, slot, -1)
        pad = np.zeros((b, k_max))
        arc = np.where(packed, snaps.arc_m[rows, slot], 0.0)
        if road.closed:
            arc = np.mod(arc, road.length_m)
        lane = np.where(packed, snaps.lane[rows, slot], 0)
        speed = np.where(packed, snaps.speed_mps[rows, slot], 0.0)
        return cls(
            lane=torch.as_tensor(np.concatenate([lane, pad], 1).astype(np.int64)),
            arc=torch.as_tensor(np.concatenate([arc, pad], 1)),
            speed=torch.as_tensor(np.concatenate([speed, pad], 1)),
            present=torch.as_tensor(np.concatenate([packed, pad.astype(bool)], 1)),
            n_obs_slots=n,
            k=k_t,
            total=torch.as_tensor(obs.sum(axis=1)) + k_t,
            source_slot=source,
        )

    def observe(
        self, step: int, idx: torch.Tensor, psi: Psi, road: Road, gen: torch.Generator
    ) -> Observation:
        """What step ``step`` sees in rows ``idx`` (those with a vehicle still to place);
        only the slots that can be filled by now (observed + ``step`` generated) enter."""
        m = self.n_obs_slots + step
        return observe(
            self.lane[idx, :m],
            self.arc[idx, :m],
            self.speed[idx, :m],
            self.present[idx, :m],
            self.k[idx] - step,
            self.total[idx],
            psi,
            road,
            _anchor(len(idx), road, gen),
        )

    def place(
        self, step: int, idx: torch.Tensor, lane: torch.Tensor, arc: torch.Tensor, v: torch.Tensor
    ) -> None:
        """Put the step's vehicle of rows ``idx`` into its slot (out of place: the training
        graph keeps every earlier step's values)."""
        j = self.n_obs_slots + step

        def put(x: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
            col = x[:, j].index_put((idx,), new)
            return torch.cat([x[:, :j], col[:, None], x[:, j + 1 :]], dim=1)

        self.lane = put(self.lane, lane)
        self.arc = put(self.arc, arc)
        self.speed = put(self.speed, v)
        self.present = put(self.present, torch.ones_like(idx, dtype=torch.bool))


def _anchor(b: int, road: Road, gen: torch.Generator) -> torch.Tensor:
    return torch.rand(b, road.max_lanes, generator=gen, dtype=torch.float64) * road.length_m


def rollout(
    net: SectionGeneratorNet,
    road: Road,
    snaps: SectionSnapshots,
    k: np.ndarray,
    gen: torch.Generator,
) -> tuple[_Scene, torch.Tensor]:
    """Training rollout (one sample per step, no rejection): the completed scenes and the
    summed log-probability of each scene's gap choices (B,)."""
    scene = _Scene.start(snaps, k, road)
    psi = Psi.of(snaps.psi)
    b = len(snaps)
    log_p = torch.zeros(b, dtype=torch.float64)
    for step in range(int(scene.k.max()) if b else 0):
        idx = torch.nonzero(scene.k > step).flatten()
        sub = psi.take(idx)
        t = propose(net, scene.observe(step, idx, sub, road, gen), sub, road, 1, gen)
        log_p = log_p.index_add(0, idx, t.log_p[:, 0])
        scene.place(step, idx, t.lane[:, 0], t.arc[:, 0], t.speed[:, 0])
    return scene, log_p


# --------------------------------------------------------------------------- inference


@dataclass
class SectionCompletion:
    """Completed scenes (S, N + K_max): the snapshot's observed vehicles in their slots
    (its hidden slots empty), then the generated ones."""

    lane: np.ndarray
    arc_m: np.ndarray
    speed_mps: np.ndarray
    valid: np.ndarray
    generated: np.ndarray
    trials: np.ndarray  # (S,) trials used over all generated vehicles
    projections: np.ndarray  # (S,) generated vehicles placed by projection
    speed_fixes: np.ndarray | None = None  # (S,) speeds changed by ``safe_speeds``
    wall_s: float = 0.0


def _k_of(snaps: SectionSnapshots, source: str) -> np.ndarray:
    """The hidden count per snapshot that the scenario's ``k_source`` asks for."""
    return np.asarray(snaps.k_true if source == "truth" else snaps.k_est, dtype=np.int64)


def _project(
    road: Road, gaps: Gaps, probs: torch.Tensor, row: int, choice: int, arc: float
) -> float:
    """The feasible point nearest to ``arc`` in gap ``choice``, else in the most likely gap
    that has one (its point nearest to the middle of its admissible part); ``arc`` if none."""
    start, lo, hi = gaps.start[row].numpy(), gaps.lo[row].numpy(), gaps.hi[row].numpy()
    lanes, valid = gaps.lane[row].numpy(), gaps.valid[row].numpy()
    order = [choice] + [
        int(j) for j in np.argsort(-probs[row].numpy(), kind="stable") if valid[j] and j != choice
    ]
    target = arc
    if road.closed and choice < len(start):  # unwrap onto the chosen gap
        target = start[choice] + np.mod(arc - start[choice], road.length_m)
    for j in order:
        a, b = start[j] + lo[j], start[j] + hi[j]
        x = road.nearest_on_lane(int(lanes[j]), a, b, target if j == choice else 0.5 * (a + b))
        if x is not None:
            return float(np.mod(x, road.length_m)) if road.closed else x
    return arc


@torch.no_grad()
def complete_section(
    net: SectionGeneratorNet,
    section: Section,
    snaps: SectionSnapshots,
    k: np.ndarray,
    t_max: int,
    seed: int,
    brake_mps2: float | None = None,
) -> SectionCompletion:
    """Algorithm 3 on a section, batched over snapshots: ``k[s]`` hidden vehicles for
    snapshot s, each from up to ``t_max`` trials, projection as the counted fallback.

    With ``brake_mps2`` (the scenario's braking bound), generated speeds are then made
    kinematically consistent with their lane neighbours (``safe_speeds``)."""
    with one_thread():
        comp = _complete(net, section, snaps, k, t_max, seed)
    if brake_mps2 is not None:
        safe_speeds(comp, section, snaps.psi[:, _PSI["spacing_min_m"]], brake_mps2)
    return comp


def generator_completion(net: SectionGeneratorNet, section: Section, sc, k_source: str, seed: int):
    """``completion(snaps)`` for ``section_env.build_section_bank``: Algorithm 3 with the
    hidden count ``k_source`` asks for (each snapshot carries both), then safe speeds."""

    def fn(s: SectionSnapshots):
        c = complete_section(
            net, section, s, _k_of(s, k_source), sc.generator.t_max, seed, -sc.bounds.accel_mps2[0]
        )
        return c.lane, c.arc_m, c.speed_mps, c.valid, c.generated

    return fn


def safe_speeds(
    comp: SectionCompletion, section: Section, standstill_m: np.ndarray, brake_mps2: float
) -> None:
    """Cap each generated vehicle's speed so that it can stop behind its leader, and raise
    it where an observed follower could not stop behind it (in place; counted in
    ``comp.speed_fixes``).

    The spacing and speed bounds say nothing about pairs: a generated vehicle 15 m/s faster
    than a leader 10 m behind satisfies both and crashes in the first second. The bound is
    the stopping-distance condition v^2 <= v_leader^2 + 2 b (spacing - standstill spacing),
    with b the action bound's braking and the standstill spacing psi's smallest spacing.
    Lanes are walked downstream to upstream, so a capped leader caps its followers.
    """
    fixes = np.zeros(len(comp.speed_mps), dtype=np.int64)
    for s in range(len(comp.speed_mps)):
        on = np.flatnonzero(comp.valid[s])
        if on.size < 2:
            continue
        lane, arc = comp.lane[s, on], comp.arc_m[s, on]
        v, gen = comp.speed_mps[s, on].copy(), comp.generated[s, on]
        leader, spacing = lane_leaders(lane, arc, section.length_m, section.closed)
        room = 2.0 * brake_mps2 * np.maximum(0.0, spacing - standstill_m[s])
        for i in np.lexsort((-arc, lane)):  # per lane, front first
            j = leader[i]
            if gen[i] and j >= 0:
                cap = math.sqrt(v[j] ** 2 + room[i])
                if v[i] > cap:
                    v[i], fixes[s] = cap, fixes[s] + 1
            if j >= 0 and gen[j] and not gen[i]:  # an observed follower must be able to stop
                floor = math.sqrt(max(0.0, v[i] ** 2 - room[i]))
                if v[j] < floor:
                    v[j], fixes[s] = floor, fixes[s] + 1
        comp.speed_mps[s, on] = v
    comp.speed_fixes = fixes


def _complete(
    net: SectionGeneratorNet,
    section: Section,
    snaps: SectionSnapshots,
    k: np.ndarray,
    t_max: int,
    seed: int,
) -> SectionCompletion:
    t0 = time.perf_counter()
    road = Road.of(section)
    gen = torch.Generator().manual_seed(int(seed))
    scene = _Scene.start(snaps, k, road)
    psi = Psi.of(snaps.psi)
    b = len(snaps)
    trials = np.zeros(b, dtype=np.int64)
    projections = np.zeros(b, dtype=np.int64)
    for step in range(int(scene.k.max()) if b else 0):
        idx = torch.nonzero(scene.k > step).flatten()
        sub = psi.take(idx)
        obs = scene.observe(step, idx, sub, road, gen)
        t = propose(net, obs, sub, road, t_max, gen)
        g = obs.gaps
        a = t.arc - g.start.gather(1, t.choice)
        if road.closed:
            a = torch.remainder(a, road.length_m)
        ok = (
            obs.choosable.gather(1, t.choice)
            & (g.room.gather(1, t.choice) >= 0)
            & (a >= g.lo.gather(1, t.choice) - TOL_M)
            & (a <= g.hi.gather(1, t.choice) + TOL_M)
            & road.has_lane(t.lane, t.arc)
            & (t.speed >= sub.v_min[:, None])
            & (t.speed <= sub.v_max[:, None])
        )
        any_ok = ok.any(dim=1)
        rows = torch.arange(len(idx))
        pick = torch.where(any_ok, ok.double().argmax(dim=1), t_max - 1)
        lane, arc, v = t.lane[rows, pick], t.arc[rows, pick].clone(), t.speed[rows, pick]
        idx_np = idx.numpy()
        trials[idx_np] += pick.numpy() + 1
        failed = np.flatnonzero(~any_ok.numpy())
        if len(failed):
            choice = t.choice[rows, pick]
            for r in failed:
                arc[r] = _project(road, g, t.probs, int(r), int(choice[r]), float(arc[r]))
            projections[idx_np[failed]] += 1
        v = torch.minimum(torch.maximum(v, sub.v_min), sub.v_max)
        scene.place(step, idx, lane, arc, v)
    return _unpack(scene, snaps, trials, projections, time.perf_counter() - t0)


def _unpack(
    scene: _Scene,
    snaps: SectionSnapshots,
    trials: np.ndarray,
    projections: np.ndarray,
    wall_s: float,
) -> SectionCompletion:
    """The completed scenes in the output layout: observed vehicles back in their snapshot
    slots (bit for bit), the generated ones after them."""
    b, n = snaps.arc_m.shape
    m = scene.n_obs_slots
    obs = np.asarray(snaps.valid & snaps.observed, dtype=bool)
    gen = scene.present[:, m:].numpy()
    return SectionCompletion(
        lane=np.concatenate([np.where(obs, snaps.lane, 0), np.where(gen, scene.lane[:, m:], 0)], 1),
        arc_m=np.concatenate(
            [np.where(obs, snaps.arc_m, 0.0), np.where(gen, scene.arc[:, m:], 0.0)], 1
        ),
        speed_mps=np.concatenate(
            [np.where(obs, snaps.speed_mps, 0.0), np.where(gen, scene.speed[:, m:], 0.0)], 1
        ),
        valid=np.concatenate([obs, gen], 1),
        generated=np.concatenate([np.zeros_like(obs), gen], 1),
        trials=trials,
        projections=projections,
        wall_s=wall_s,
    )


def uniform_completion(
    net: SectionGeneratorNet | None,
    section: Section,
    snaps: SectionSnapshots,
    k: np.ndarray,
    t_max: int,
    seed: int,
) -> SectionCompletion:
    """Baseline: hidden vehicles at uniform positions on the section, a lane drawn uniformly
    among those the edge there has, at psi's mean speed (no bounds checked; ``net`` and
    ``t_max`` are unused: the signature is ``complete_section``'s)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng([int(seed), 303])
    b, n = snaps.arc_m.shape
    k = np.maximum(np.asarray(k, dtype=np.int64), 0)
    k_max = int(k.max()) if b else 0
    gen_mask = np.arange(k_max)[None, :] < k[:, None]
    arc = rng.uniform(0.0, section.length_m, (b, k_max))
    lanes_there = section.n_lanes[section.edge_index(arc)]
    lane = np.floor(rng.random((b, k_max)) * lanes_there).astype(np.int64)
    obs = snaps.valid & snaps.observed
    v_mean = snaps.psi[:, _PSI["mean_speed_mps"]]
    return SectionCompletion(
        lane=np.concatenate([np.where(obs, snaps.lane, 0), np.where(gen_mask, lane, 0)], 1),
        arc_m=np.concatenate([np.where(obs, snaps.arc_m, 0.0), np.where(gen_mask, arc, 0.0)], 1),
        speed_mps=np.concatenate(
            [np.where(obs, snaps.speed_mps, 0.0), np.where(gen_mask, v_mean[:, None], 0.0)], 1
        ),
        valid=np.concatenate([obs, gen_mask], 1),
        generated=np.concatenate([np.zeros_like(obs), gen_mask], 1),
        trials=np.zeros(b, dtype=np.int64),
        projections=np.zeros(b, dtype=np.int64),
        wall_s=time.perf_counter() - t0,
    )


# --------------------------------------------------------------------------- checks, metrics


def _scene_spacings(
    lane: np.ndarray, arc: np.ndarray, section: Section
) -> tuple[np.ndarray, np.ndarray]:
    """Leader index and spacing of one scene's vehicles; NaN spacing where there is no leader."""
    leader, sp = lane_leaders(lane, arc, section.length_m, section.closed)
    return leader, np.where(leader >= 0, sp, np.nan)


def completion_violations(
    section: Section, snaps: SectionSnapshots, comp: SectionCompletion
) -> pd.DataFrame:
    """Per snapshot, generated vehicles that break a bound: spacing below psi's minimum to
    the vehicle ahead or behind in the lane, speed outside psi's range, a lane the edge
    lacks (``spacing``, ``speed``, ``lane`` counts)."""
    rows = []
    s_min = snaps.psi[:, _PSI["spacing_min_m"]]
    v_lo, v_hi = snaps.psi[:, _PSI["speed_min_mps"]], snaps.psi[:, _PSI["speed_max_mps"]]
    for i in range(len(snaps)):
        idx = np.flatnonzero(comp.valid[i])
        gen = comp.generated[i, idx]
        lane, arc = comp.lane[i, idx], comp.arc_m[i, idx]
        leader, sp = _scene_spacings(lane, arc, section)
        close = np.nan_to_num(sp, nan=np.inf) < s_min[i] - TOL_M
        # a close pair counts against the generated vehicle at either end of it
        bad = close & gen
        bad[leader[close & ~gen]] |= gen[leader[close & ~gen]]
        v = comp.speed_mps[i, idx][gen]
        lanes_there = section.n_lanes[section.edge_index(arc[gen])]
        rows.append(
            {
                "spacing": int(bad.sum()),
                "speed": int(((v < v_lo[i] - 1e-9) | (v > v_hi[i] + 1e-9)).sum()),
                "lane": int((lane[gen] >= lanes_there).sum()),
            }
        )
    return pd.DataFrame(rows)


def _spacing_stats(lane: np.ndarray, arc: np.ndarray, section: Section) -> tuple[float, float]:
    _, sp = _scene_spacings(lane, arc, section)
    sp = sp[np.isfinite(sp)]
    return (float(sp.mean()), float(sp.std())) if len(sp) else (np.nan, np.nan)


def completion_metrics(
    section: Section, snaps: SectionSnapshots, comp: SectionCompletion, k: np.ndarray
) -> pd.DataFrame:
    """Per snapshot: completed mean speed vs psi and truth, spacing mean/std vs truth (the
    first vehicle of a lane on an open section left out), K used vs k_true, trials,
    projections, bound violations of the generated vehicles."""
    viol = completion_violations(section, snaps, comp)
    out = []
    for i in range(len(snaps)):
        c = comp.valid[i]
        t = snaps.valid[i]
        mean_c, std_c = _spacing_stats(comp.lane[i, c], comp.arc_m[i, c], section)
        mean_t, std_t = _spacing_stats(snaps.lane[i, t], snaps.arc_m[i, t], section)
        out.append(
            {
                "run": snaps.run[i],
                "time_s": snaps.time_s[i],
                "n_observed": int((snaps.valid[i] & snaps.observed[i]).sum()),
                "k_used": int(k[i]),
                "k_true": int(snaps.k_true[i]),
                "psi_mean_speed_mps": snaps.psi[i, _PSI["mean_speed_mps"]],
                "mean_speed_mps": comp.speed_mps[i, c].mean() if c.any() else np.nan,
                "true_mean_speed_mps": snaps.speed_mps[i, t].mean() if t.any() else np.nan,
                "std_speed_mps": comp.speed_mps[i, c].std() if c.any() else np.nan,
                "true_std_speed_mps": snaps.speed_mps[i, t].std() if t.any() else np.nan,
                "psi_mean_spacing_m": snaps.psi[i, _PSI["mean_spacing_m"]],
                "mean_spacing_m": mean_c,
                "true_mean_spacing_m": mean_t,
                "psi_std_spacing_m": snaps.psi[i, _PSI["std_spacing_m"]],
                "std_spacing_m": std_c,
                "true_std_spacing_m": std_t,
                "trials": int(comp.trials[i]),
                "projections": int(comp.projections[i]),
            }
        )
    df = pd.DataFrame(out)
    df["speed_err_vs_psi_mps"] = (df["mean_speed_mps"] - df["psi_mean_speed_mps"]).abs()
    df["spacing_std_ratio"] = df["std_spacing_m"] / df["true_std_spacing_m"]
    df["violations"] = viol.sum(axis=1).to_numpy()
    df["feasible"] = df["violations"] == 0
    return df


# --------------------------------------------------------------------------- checkpoints


def signature(sc: SectionScenario) -> dict[str, Any]:
    """What a section generator depends on: a checkpoint is only valid for the same values."""
    return {
        "section.edges": list(sc.section.edges),
        "section.closed": bool(sc.section.closed),
        "simulation.step_length_s": float(sc.simulation.step_length_s),
        "observation_layout": f"section-gaps-v{FEATURE_VERSION}",
    }


def save_section_generator(
    path: Path, net: SectionGeneratorNet, sc: SectionScenario, extra: dict[str, Any] | None = None
) -> None:
    """Write ``generator.pt`` atomically (a crash never leaves a half-written checkpoint)."""
    save_network(path, CHECKPOINT_FORMAT, net, signature(sc), sc.to_dict(), extra)


def load_section_generator(path: Path | str, sc: SectionScenario) -> SectionGeneratorNet:
    """Load a section ``generator.pt``; a corrupt file or one trained for another section is
    a one-line UserError naming the file and what differs."""
    return load_network(
        path,
        CHECKPOINT_FORMAT,
        "section generator",
        signature(sc),
        SectionGeneratorNet,
        sc.source or sc.name,
    )


# --------------------------------------------------------------------------- training


def _batch_loss(
    net: SectionGeneratorNet,
    road: Road,
    snaps: SectionSnapshots,
    k: np.ndarray,
    sc: SectionScenario,
    gen: torch.Generator,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Surrogate loss of one batch (reparameterised terms + score-function term for the gap
    choices, batch-mean baseline) and the batch means of every term."""
    scene, log_p = rollout(net, road, snaps, k, gen)
    terms = section_losses(
        scene.lane,
        scene.arc,
        scene.speed,
        scene.present,
        Psi.of(snaps.psi, speed_spread_target(snaps)),
        road,
    )
    loss = macro_loss(terms, sc.generator.lambda_v, sc.generator.lambda_d)
    advantage = (loss - loss.mean()).detach()
    surrogate = loss.mean() + (advantage * log_p).mean()
    stats = {name: float(v.detach().mean()) for name, v in terms.items()}
    return surrogate, stats | {"loss": float(loss.detach().mean())}


def _eval_loss(
    net: SectionGeneratorNet,
    road: Road,
    snaps: SectionSnapshots,
    k: np.ndarray,
    sc: SectionScenario,
    seed: int,
) -> dict[str, float]:
    """Mean of every term over ``snaps`` with a fixed seed (validation: comparable epochs)."""
    gen = torch.Generator().manual_seed(seed)
    sums: dict[str, float] = {}
    with torch.no_grad():
        for s in range(0, len(snaps), EVAL_BATCH):
            idx = np.arange(s, min(s + EVAL_BATCH, len(snaps)))
            _, st = _batch_loss(net, road, snaps.take(idx), k[idx], sc, gen)
            for name, v in st.items():
                sums[name] = sums.get(name, 0.0) + v * len(idx)
    return {name: v / max(len(snaps), 1) for name, v in sums.items()}


def train_section_generator(
    sc: SectionScenario,
    section: Section,
    train: SectionSnapshots,
    val: SectionSnapshots,
    progress: bool = True,
    *,
    out: Path | None = None,
    epochs: int | None = None,
) -> tuple[SectionGeneratorNet, pd.DataFrame]:
    """Algorithm 2 on a section: minibatches of training snapshots, early stopping on the
    validation snapshots' loss. Returns the best network and the per-epoch log.

    ``out``: write ``generator.pt`` there (atomically) on every improvement, so an
    interrupted run keeps its best weights. ``epochs`` overrides ``sc.generator.epochs``.
    """
    with one_thread():
        return _train(sc, section, train, val, progress, out, epochs)


def _train(
    sc: SectionScenario,
    section: Section,
    train: SectionSnapshots,
    val: SectionSnapshots,
    progress: bool,
    out: Path | None,
    epochs: int | None,
) -> tuple[SectionGeneratorNet, pd.DataFrame]:
    cfg = sc.generator
    torch.manual_seed(sc.seed)
    road = Road.of(section)
    net = SectionGeneratorNet(cfg.hidden_size)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    gen = torch.Generator().manual_seed(sc.seed)
    rng = np.random.default_rng([sc.seed, 31])
    k_train, k_val = _k_of(train, cfg.k_source), _k_of(val, cfg.k_source)
    best, best_state, bad, log = math.inf, copy.deepcopy(net.state_dict()), 0, []
    t0 = time.perf_counter()
    bar = tqdm(
        range(epochs or cfg.epochs),
        desc="train-section-generator",
        unit="epoch",
        disable=not progress,
    )
    for epoch in bar:
        net.train()
        perm = rng.permutation(len(train))
        stats = []
        for s in range(0, len(perm), cfg.batch_size):
            idx = perm[s : s + cfg.batch_size]
            loss, st = _batch_loss(net, road, train.take(idx), k_train[idx], sc, gen)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
            opt.step()
            stats.append((st, len(idx)))
        net.eval()
        vs = _eval_loss(net, road, val, k_val, sc, sc.seed + 17)
        n_tr = sum(w for _, w in stats)
        row = {
            "epoch": epoch,
            "wall_s": time.perf_counter() - t0,
            **{f"train_{k}": sum(s[k] * w for s, w in stats) / n_tr for k in stats[0][0]},
            **{f"val_{k}": v for k, v in vs.items()},
        }
        log.append(row)
        if vs["loss"] < best - 1e-9:
            best, best_state, bad = vs["loss"], copy.deepcopy(net.state_dict()), 0
            if out is not None:
                save_section_generator(
                    Path(out) / "generator.pt", net, sc, {"epoch": epoch, "val_loss": best}
                )
        else:
            bad += 1
        bar.set_postfix(train=f"{row['train_loss']:.4f}", val=f"{vs['loss']:.4f}")
        if bad >= cfg.patience:
            break
    net.load_state_dict(best_state)
    net.eval()
    return net, pd.DataFrame(log)


def run_train_section_generator(
    sc: SectionScenario, data: Path, out: Path, command: str = "", progress: bool = True
) -> dict[str, Any]:
    """CLI stage: split the ground truth's runs, train, evaluate on the held-out runs; write
    generator.pt, generator_train_log.csv, generator_metrics.csv (per held-out snapshot,
    generator and uniform baseline) and generator_manifest.json."""
    truth = load_section_truth(Path(data), sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    train = section_snapshots(truth, sc, splits["train"])
    val = section_snapshots(truth, sc, splits["val"]) if len(splits["val"]) else train
    held = section_snapshots(truth, sc, splits["held_out"])
    out = prepare_out_dir(out)  # only once the inputs are known to be good
    t0 = time.perf_counter()
    net, log = train_section_generator(sc, truth.section, train, val, progress, out=out)
    train_s = time.perf_counter() - t0
    save_section_generator(out / "generator.pt", net, sc, {"epochs": len(log)})
    write_csv(log, out / "generator_train_log.csv")
    k = _k_of(held, sc.generator.k_source)
    frames, timings = [], {"train_generator": round(train_s, 3)}
    for method, fn in (("generator", complete_section), ("uniform", uniform_completion)):
        comp = fn(net, truth.section, held, k, sc.generator.t_max, sc.seed)
        timings[f"complete_{method}"] = round(comp.wall_s, 3)
        m = completion_metrics(truth.section, held, comp, k)
        m.insert(0, "method", method)
        frames.append(m)
    metrics = pd.concat(frames, ignore_index=True)
    write_csv(metrics, out / "generator_metrics.csv")
    summary = {
        method: {
            "snapshots": int(len(g)),
            "speed_err_vs_psi_mps": float(g["speed_err_vs_psi_mps"].mean()),
            "spacing_std_ratio": float(g["std_spacing_m"].mean() / g["true_std_spacing_m"].mean()),
            "speed_std_ratio": float(g["std_speed_mps"].mean() / g["true_std_speed_mps"].mean()),
            "feasible_share": float(g["feasible"].mean()),
            "projections": int(g["projections"].sum()),
        }
        for method, g in metrics.groupby("method")
    }
    manifest = build_manifest(sc, command, stage="train-section-generator")  # type: ignore[arg-type]
    manifest.update(
        ground_truth=str(data),
        splits={name: v.tolist() for name, v in splits.items()},
        epochs=len(log),
        best_val_loss=float(log["val_loss"].min()) if len(log) else None,
        timings_s=timings,
        summary=summary,
    )
    write_json(manifest, out / "generator_manifest.json")
    return manifest

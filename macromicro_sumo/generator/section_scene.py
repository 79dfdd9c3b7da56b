"""Stage I on a road section: the scene a completion works on (road, psi, gaps).

The ring generator (``ring_model``) places K hidden vehicles in the gaps of one lane
loop. On a road section the scene is a section of a user's network: several lanes, lane
counts that change from edge to edge, an open corridor (vehicles enter upstream and leave
downstream) or a closed loop, and a hidden count K that varies per snapshot (estimated
from the detectors' density). The method is the same (Algorithms 2 and 3 of the paper):
the network is ``section_model``, Algorithm 3 ``section_sampler``, training
``section_train``.

Lanes are numbered along the network's lane connections (``section_lanes``): a lane keeps
its number where the through lane changes SUMO index at a junction, so a gap's leader is
the next vehicle along the connections (``section_leaders``' leader).

Gaps. Every lane is cut by its vehicles into gaps: between consecutive vehicles, and on
an open section the two open ends (upstream of the lane's last vehicle, downstream of its
first); on a closed section the last gap wraps around the loop. An empty lane is one gap
of the section's length (closed: from a random anchor, the loop has no start).

Geometry is torch (float64 for positions), one definition for the training rollout (with
gradients) and for inference (no_grad, T_max trials per step at once, batched over
snapshots).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from macromicro_sumo.data.section import PSI_FIELDS, SectionSnapshots
from macromicro_sumo.generator.section_lanes import END_MARGIN_M, Road
from macromicro_sumo.road.section import Section

TOL_M = 1e-6  # rounding allowed in the spacing check [m]

PSI_INDEX = {name: i for i, name in enumerate(PSI_FIELDS)}


# --------------------------------------------------------------------------- road and psi


def extra_lengths(snaps: SectionSnapshots) -> np.ndarray:
    """(S, N) each recorded vehicle's length beyond the snapshots' shortest [m], 0 where no
    vehicle is: psi's s_min is the shortest vehicle plus the minimum gap, so a longer
    leader (a truck) keeps this much more free behind it (``scene_gaps``, ``safe_speeds``)."""
    valid = np.asarray(snaps.valid, dtype=bool)
    lengths = np.asarray(snaps.length_m, dtype=float)
    return np.where(valid, np.maximum(lengths - shortest_length(snaps), 0.0), 0.0)


def shortest_length(snaps: SectionSnapshots) -> float:
    """The snapshots' shortest recorded vehicle [m] (0 where none is): the length psi's
    s_min holds (``extra_lengths``)."""
    valid = np.asarray(snaps.valid, dtype=bool)
    return float(np.asarray(snaps.length_m, dtype=float)[valid].min()) if valid.any() else 0.0


def generated_extra(snaps: SectionSnapshots, length_m: float | None) -> float:
    """The generated vehicles' length beyond the snapshots' shortest [m] (0: None, or not
    longer). Placed at psi's s_min (the shortest vehicle plus the minimum gap) a 5 m
    generated car left its follower 1.5 m of a 2.0 m minimum gap behind a 4.5 m car's
    spacing (fresh 1169, stop 46): ``complete_section`` places each with this much more
    room behind it (``scene_gaps``' ``new_extra``) and keeps it ahead of the next
    (``Scene.extra``)."""
    if length_m is None or not len(snaps):
        return 0.0
    return max(float(length_m) - shortest_length(snaps), 0.0)


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
    d_max: torch.Tensor  # largest spacing (inf: none; ``generator.spacing_bounds``)
    d_min: torch.Tensor  # shortest spacing to place at (s_min unless spacing_bounds)

    # speed spread target [m/s] (NaN where unknown; ``speed_spread_target``)
    v_std: torch.Tensor | None = None

    @classmethod
    def of(cls, psi: np.ndarray, v_std: np.ndarray | None = None) -> Psi:
        p = torch.as_tensor(np.asarray(psi, dtype=np.float64))
        d_std = p[:, PSI_INDEX["std_spacing_m"]]
        known = torch.isfinite(d_std)
        s_min = p[:, PSI_INDEX["spacing_min_m"]]

        def column(name: str, default: torch.Tensor) -> torch.Tensor:
            # psi arrays written before the field existed have no column: the default
            return p[:, PSI_INDEX[name]] if p.shape[1] > PSI_INDEX[name] else default

        return cls(
            v_mean=p[:, PSI_INDEX["mean_speed_mps"]],
            d_mean=p[:, PSI_INDEX["mean_spacing_m"]],
            d_std=torch.where(known, d_std, 0.0),
            d_std_known=known,
            v_min=p[:, PSI_INDEX["speed_min_mps"]],
            v_max=p[:, PSI_INDEX["speed_max_mps"]],
            s_min=s_min,
            d_max=column("spacing_max_m", torch.full_like(s_min, math.inf)),
            d_min=torch.maximum(s_min, column("spacing_low_m", s_min)),
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
    # the gap's leader's length beyond the shortest vType's [m] (its s_min is the shortest's)
    extra_l: torch.Tensor
    # the new vehicle's own length beyond the shortest's [m]: its follower keeps this much
    # more behind it (``scene_gaps``' ``new_extra``; lo holds it, ``kinematic_speeds`` too)
    extra_new: torch.Tensor

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
    extra: torch.Tensor | None = None,
    new_extra: float = 0.0,
) -> Gaps:
    """The gaps of the current scenes (``Gaps``); ``anchor`` (B, lanes) is where an empty
    lane's gap starts on a closed section; ``extra`` (B, M) each vehicle's length beyond
    the shortest vType's (None: 0), which a new vehicle keeps behind it on top of s_min
    (s_min is the shortest vehicle plus the minimum gap: with it alone a car was put
    inside an observed 12 m truck); ``new_extra`` the new vehicle's own
    (``generated_extra``), which the gap's follower keeps behind it (0: psi's s_min)."""
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
    ex = torch.zeros_like(arc) if extra is None else extra.to(arc.dtype)
    ex_first = ex.gather(1, lo_["first_slot"])  # (B, lanes): each lane's first vehicle's
    ex_next = torch.cat([ex.gather(1, lo_["order"])[:, 1:], ex_first[:, :1]], dim=1)
    ex_l = torch.where(lo_["has_next"], ex_next, ex_first.gather(1, lane_c))
    ex_l = torch.where(has_l, ex_l, 0.0)
    lo = (s_min_c + new_extra).expand(b, m)
    hi = length - torch.where(has_l, s_min_c + ex_l, END_MARGIN_M)
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
        h_lo = torch.zeros(b, nl, dtype=torch.float64)
        h_has_f, h_v_f = torch.zeros_like(occupied), torch.zeros_like(h_len)
    else:
        first_arc = lo_["first_arc"]
        # A lane a fan-out begins (``Road.feeder``): its head gap starts at the feeding
        # lane's last vehicle before the branch, that vehicle its follower (the envs'
        # leader search sees a vehicle at the branch's start ahead of it).
        f_has, f_arc, f_v = _feeders(lane, arc, speed, present, road)
        h_start = torch.where(f_has, f_arc, 0.0)
        h_len = torch.where(occupied, first_arc, road.length_m) - h_start
        h_hi = torch.where(occupied, h_len - s_min_c - ex_first, h_len - END_MARGIN_M)
        h_valid = torch.ones_like(occupied)
        h_has_l = occupied
        h_v_l = torch.where(occupied, first_v, 0.0)
        h_lo = torch.where(f_has, s_min_c + new_extra, 0.0)
        h_has_f, h_v_f = f_has, torch.where(f_has, f_v, 0.0)
    return Gaps(
        start=torch.cat([lo_["arc"], h_start], dim=1),
        length=torch.cat([length, h_len], dim=1),
        lo=torch.cat([lo, h_lo], dim=1),
        hi=torch.cat([hi, h_hi], dim=1),
        lane=torch.cat([lo_["lane"], lanes], dim=1),
        has_f=torch.cat([lo_["present"], h_has_f], dim=1),
        has_l=torch.cat([has_l, h_has_l], dim=1),
        v_f=torch.cat([torch.where(lo_["present"], s_v, 0.0), h_v_f], dim=1),
        v_l=torch.cat([torch.where(has_l, v_l, 0.0), h_v_l], dim=1),
        valid=torch.cat([lo_["present"], h_valid], dim=1),
        n_lane=torch.cat([count.gather(1, lane_c), count], dim=1).double(),
        extra_l=torch.cat([ex_l, torch.where(h_has_l, ex_first, 0.0)], dim=1),
        extra_new=torch.full((b, m + nl), float(new_extra), dtype=torch.float64),
    )


def _feeders(
    lane: torch.Tensor, arc: torch.Tensor, speed: torch.Tensor, present: torch.Tensor, road: Road
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B, lanes) whether each lane has a follower from a fan-out (``Road.feeder``: the last
    vehicle of the feeding lane upstream of where it begins), its arc and speed."""
    fed = road.feeder >= 0
    if not bool(fed.any()):
        z = torch.zeros(arc.shape[0], road.max_lanes, dtype=torch.float64)
        return torch.zeros_like(z, dtype=torch.bool), z, z
    on = (lane[..., None] == road.feeder) & present[..., None] & fed
    on = on & (arc.detach()[..., None] < road.branch_m)  # (B, M, lanes)
    key = torch.where(on, arc.detach()[..., None], -math.inf)
    slot = key.argmax(dim=1)  # (B, lanes)
    return on.any(dim=1), arc.gather(1, slot), speed.gather(1, slot)


def scene_stops(section: Section, snaps: SectionSnapshots) -> tuple[np.ndarray, np.ndarray] | None:
    """(S, P) lane index and arc (NaN: padding) of the standing obstacles each scene's
    generated vehicles must be able to stop at: the snapshot's red or yellow stop lines
    (``SectionSnapshots.stop_lane``) and the end of every lane that does not continue along
    the section (``Section.route_ends``, as the envs' driven vehicles see them: a lane end,
    a turning lane; SUMO stops one that has not left such a lane at its end). None: there
    are none."""
    ends = [
        (ln, float(section.offsets_m[e] + section.lengths_m[e]))
        for e, ln in zip(*np.nonzero(section.route_ends), strict=True)
    ]
    s = len(snaps)
    lane = np.tile(np.array([x for x, _ in ends], dtype=np.int64), (s, 1))
    arc = np.tile(np.array([x for _, x in ends], dtype=float), (s, 1))
    if snaps.stop_arc_m is not None:
        lane = np.concatenate([lane, snaps.stop_lane], axis=1)
        arc = np.concatenate([arc, snaps.stop_arc_m], axis=1)
    return (lane, arc) if np.isfinite(arc).any() else None


def stop_room_m(
    lane: torch.Tensor, arc: torch.Tensor, stops: tuple[torch.Tensor, torch.Tensor], road: Road
) -> torch.Tensor:
    """(B, n) distance [m] from candidates at (``lane``, ``arc``) to the nearest red or
    yellow stop line ahead on their lane (``stops``: (B, P) lane, arc; inf arc: none), inf
    where there is none: a standing leader there (``safe_speeds``' ``stops``)."""
    ahead = stops[1][:, None, :] - arc[..., None]  # (B, n, P)
    if road.closed:
        ahead = torch.remainder(ahead, road.length_m)
    mine = (stops[0][:, None, :] == lane[..., None]) & (ahead >= -TOL_M) & torch.isfinite(ahead)
    return torch.where(mine, ahead.clamp(min=0.0), math.inf).amin(dim=-1)


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


def dispersion_budget(gaps: Gaps, total: torch.Tensor, psi: Psi, road: Road) -> torch.Tensor:
    """(B, G) the share of the completed scene's spacing dispersion still missing if the
    next vehicle splits each gap in its middle: 1 - S_j / (n sigma^2), S_j the spacings'
    summed squared deviation from the completed scene's mean spacing (a closed section's
    exact lane length / n, psi's on an open one) with gap j halved, n the completed
    scene's vehicles, sigma psi's spacing std; in [-5, 1], 0 where psi has none.

    Why (``generator.dispersion_feature``): the gap features and psi say nothing about
    the spacings elsewhere in the scene, so a position head cannot tell how far from its
    gap's middle a vehicle must go for the scene to reach psi's spread. On the ring as a
    section the last vehicle then sat 0.08-0.09 of its gap off the middle at every K,
    whether the scene before it (that gap halved) held 0.69 sigma^2 (K = 1, observed
    spacings) or 0.95 sigma^2 (K = 4, earlier generated ones): K = 1's spread came out
    3.9% short. Read beside ``spacing_set = "touched"`` (the ring's A: the observed
    spacings keep their own spread); with every spacing in A the net met psi's sigma^2 in
    every scene and the scenes came out 3-7% too wide (docs/design.md, "Ring as a
    section: status", item 3)."""
    n = total.double().clamp(min=1.0)
    center = road.lane_length_m / n if road.closed else psi.d_mean
    m = gaps.length.shape[1] - road.max_lanes  # vehicle gaps first, then one head gap per lane
    length = gaps.length[:, :m].detach()
    spacing = gaps.valid[:, :m] & gaps.has_l[:, :m]
    dev = torch.where(spacing, (length - center[:, None]) ** 2, 0.0)
    s_now = dev.sum(dim=1, keepdim=True)
    between = spacing & gaps.has_f[:, :m]
    halved = s_now - dev + 2.0 * (0.5 * length - center[:, None]) ** 2
    s_mid = torch.cat(
        [torch.where(between, halved, s_now), s_now.expand(-1, road.max_lanes)], dim=1
    )
    known = psi.d_std_known & (psi.d_std > 0)
    target = (n * psi.d_std**2).clamp(min=1e-9)[:, None]
    budget = (1.0 - s_mid / target).clamp(-5.0, 1.0)
    return torch.where(known[:, None] & gaps.valid, budget, 0.0)

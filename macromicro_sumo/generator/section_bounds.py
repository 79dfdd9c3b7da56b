"""psi's largest spacing on a section (``generator.spacing_bounds = "passages"``) and the
ring's A (``generator.spacing_set = "touched"``): which gaps a generated vehicle touches,
and where the next vehicle may go so that the touched gaps can still end within d_max.

Why: without an upper bound the completions' spacing spread had a long right tail (the
paper's ring as a section, K = 2..4: mean scene variance 1.09-1.16 x psi's where the
truth's is 0.97 x; spacing std +3.5 / +5.5 / +3.8% against the truth). The ring has
psi's [d_min, d_max] from the passages and its exact look-ahead (the ring wing, removed in stop 25).

As on the ring the bounds act at inference only, by rejection (Algorithm 3,
``complete_section``): the proposal places between s_min and the gap's end in training and
inference alike and learns the bounds from L_min / L_max. Truncating in training too
trained worse (validation L_var 0.023 at ~100 epochs against 0.012-0.017 without); a
proposal squeezed into the bounded part at inference only narrowed the completions
(spacing std -13..-24% by K).
"""

from __future__ import annotations

import dataclasses

import torch

from macromicro_sumo.generator.section_scene import Gaps, Psi, Road, lane_order


def touched_gaps(lo_: dict[str, torch.Tensor], generated_from: int, road: Road) -> torch.Tensor:
    """(B, M) whether the gap ahead of each sorted vehicle (``lane_order``) has a generated
    vehicle (slot >= ``generated_from``) at either end: the ring's A."""
    gen = lo_["order"] >= generated_from
    around = lo_["first_slot"].gather(1, lo_["lane"].clamp(0, road.max_lanes - 1))
    lead = torch.where(
        lo_["has_next"], torch.cat([gen[:, 1:], gen[:, -1:]], dim=1), around >= generated_from
    )
    return (gen | lead) & lo_["has_l"] & lo_["present"]


def cap_pieces(
    gaps: Gaps, remaining: torch.Tensor, d_max: torch.Tensor, touched: torch.Tensor | None = None
) -> Gaps:
    """``gaps`` with psi's largest spacing d kept where it can be. A gap touched by a
    generated vehicle (``touched``; None: none yet) and longer than d needs
    ceil(g / d) - 1 more vehicles. The next vehicle may go into gap j only if the r - 1
    after it cover what the other touched gaps need (slack c_j >= 0) and its two pieces
    can then end within d: anywhere if g <= (c_j + 1) d (pieces needing c1 + c2 <= c_j),
    else (g <= (c_j + 2) d) with the piece behind it within d, the one ahead within
    (c_j + 1) d; never where g > (c_j + 2) d. Exact for the count of vehicles (the ring's
    look-ahead also keeps d_min); a gap whose room closes is not chosen (``observe``'s
    ``choosable``); gaps without two vehicles (an empty loop, open ends) are not capped."""
    d = d_max[:, None]
    both = gaps.has_f & gaps.has_l & gaps.valid
    need = torch.zeros_like(gaps.length)
    if touched is not None:
        need = torch.where(touched & both, (gaps.length / d - 1e-9).ceil() - 1.0, 0.0)
        need = need.clamp(min=0.0)
    r = remaining.double().clamp(min=1.0)[:, None]
    slack = r - 1.0 - (need.sum(dim=1, keepdim=True) - need)
    g = gaps.length
    anywhere = g <= (slack + 1.0) * d
    lo = torch.where(both & ~anywhere, torch.maximum(gaps.lo, g - (slack + 1.0) * d), gaps.lo)
    hi = torch.where(both & ~anywhere, torch.minimum(gaps.hi, d.expand_as(g)), gaps.hi)
    closed = gaps.valid & (slack < 0) | both & (g > (slack + 2.0) * d)
    hi = torch.where(closed & torch.isfinite(d), lo - 1.0, hi)
    return dataclasses.replace(gaps, lo=lo, hi=hi)


def bounded_gaps(
    gaps: Gaps,
    lane: torch.Tensor,
    arc: torch.Tensor,
    present: torch.Tensor,
    remaining: torch.Tensor,
    psi: Psi,
    road: Road,
    generated_from: int,
) -> Gaps | None:
    """``gaps`` (``scene_gaps`` with s_min) with the parts Algorithm 3 accepts under psi's
    [d_min, d_max]: both pieces >= d_min, touched gaps completable within d_max
    (``cap_pieces``). None where psi has no bound beyond s_min (nothing changes)."""
    if not bool(torch.isfinite(psi.d_max).any() | (psi.d_min > psi.s_min).any()):
        return None
    d_min = psi.d_min[:, None]
    lo = torch.where(gaps.has_f, torch.maximum(gaps.lo, d_min), gaps.lo)
    hi = torch.where(gaps.has_l, torch.minimum(gaps.hi, gaps.length - d_min), gaps.hi)
    out = dataclasses.replace(gaps, lo=lo, hi=hi)
    lo_ = lane_order(lane, arc, present, road)
    head = torch.zeros(len(arc), road.max_lanes, dtype=torch.bool)
    touched = torch.cat([touched_gaps(lo_, generated_from, road), head], dim=1)
    return cap_pieces(out, remaining, psi.d_max, touched)

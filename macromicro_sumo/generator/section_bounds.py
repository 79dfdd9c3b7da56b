"""psi's largest spacing on a section (``generator.spacing_bounds = "passages"``) and the
ring's A (``generator.spacing_set = "touched"``): which gaps a generated vehicle touches,
and where the next vehicle may go so that the touched gaps can still end within d_max.

Why: without an upper bound the completions' spacing spread had a long right tail (the
paper's ring as a section, K = 2..4: mean scene variance 1.09-1.16 x psi's where the
truth's is 0.97 x; spacing std +3.5 / +5.5 / +3.8% against the truth). The ring has
psi's [d_min, d_max] from the passages and its exact look-ahead (``ring_posterior``).
"""

from __future__ import annotations

import dataclasses

import torch

from macromicro_sumo.generator.section_scene import Gaps, Road


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
    """``gaps`` with psi's largest spacing d_max kept where it can be: a gap touched by a
    generated vehicle (``touched``; None: none yet) longer than d_max needs
    ceil(g / d_max) - 1 more vehicles. The next vehicle may go into gap j only if the
    r - 1 after it cover what the other touched gaps need (the slack c_j >= 0), and only
    where both pieces stay within (c_j + 1) d_max, so that they can still be split within
    it (exact for the last vehicle; the ring's look-ahead also counts d_min and which
    splits are integral). A gap whose room closes is not chosen (``observe``'s
    ``choosable``); gaps without two vehicles (an empty loop, open ends) are not capped."""
    d = d_max[:, None]
    both = gaps.has_f & gaps.has_l & gaps.valid
    need = torch.zeros_like(gaps.length)
    if touched is not None:
        need = torch.where(touched & both, (gaps.length / d - 1e-9).ceil() - 1.0, 0.0)
        need = need.clamp(min=0.0)
    r = remaining.double().clamp(min=1.0)[:, None]
    slack = r - 1.0 - (need.sum(dim=1, keepdim=True) - need)
    cap = (slack + 1.0) * d
    lo = torch.where(both, torch.maximum(gaps.lo, gaps.length - cap), gaps.lo)
    hi = torch.where(both, torch.minimum(gaps.hi, cap), gaps.hi)
    # a gap with no slack left (or an uncapped one) can take no vehicle
    closed = (slack < 0) & gaps.valid & torch.isfinite(d)
    hi = torch.where(closed, lo - 1.0, hi)
    return dataclasses.replace(gaps, lo=lo, hi=hi)

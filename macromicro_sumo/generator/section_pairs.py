"""Stage I's last check of a completed scene: every pair along the network's lanes with a
generated vehicle in it can be driven, or the generated vehicle is dropped (counted).

The placement works on gaps per lane index (``section_scene``), where a lane index means the
same lane along the arc. Where the through lane changes index at a junction (drawn net 501:
lane 1 of a two-lane edge continues onto lane 0 of a one-lane edge), two vehicles one
behind the other on the network are on two lane indices there: the gaps let a generated
car stand 0.6 m behind another, or 6.5 m ahead of an observed car at 21 m/s with a slow
car ahead of it that ``safe_speeds`` must keep it behind (Stage II evaluation collisions in
the first step). ``section_leaders`` follows the lane connections; a pair that overlaps or
whose follower cannot stop behind its leader loses its generated vehicle (the follower
where it is generated, else the leader), as a vehicle that fits nowhere is dropped.
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.road.section import STOP, Section, section_leaders

TOL = 1e-6


def drop_unsafe_pairs(
    comp,
    section: Section,
    standstill_m: np.ndarray,
    brake_mps2: float,
    reaction_s: float,
    extra_m: np.ndarray,
    stops: tuple[np.ndarray, np.ndarray] | None,
) -> np.ndarray:
    """Drop (in place: ``valid`` and ``generated`` False) generated vehicles of pairs that
    overlap (front-to-front spacing below the standstill spacing plus the leader's extra
    length) or whose follower cannot stop behind its leader (``safe_speeds``' condition,
    a red light or lane end a standing leader); returns the drops per scene (S,)."""
    bt = brake_mps2 * reaction_s
    dropped = np.zeros(len(comp.valid), dtype=np.int64)
    for s in range(len(comp.valid)):
        stop_lane = stop_arc = None
        if stops is not None:
            ok = np.isfinite(stops[1][s])
            stop_lane, stop_arc = stops[0][s][ok], stops[1][s][ok]
        while True:
            on = np.flatnonzero(comp.valid[s])
            if not comp.generated[s, on].any():
                break
            lane, arc, v = comp.lane[s, on], comp.arc_m[s, on], comp.speed_mps[s, on]
            gen, ex = comp.generated[s, on], extra_m[s, on]
            lead, spacing = section_leaders(section, lane, arc, stop_lane, stop_arc)
            has = lead >= 0
            j = np.maximum(lead, 0)
            ex_l = np.where(has, ex[j], 0.0)
            v_l = np.where(has, v[j], 0.0)
            free = spacing - standstill_m[s] - ex_l
            cannot_stop = (
                v * v + 2.0 * bt * v
                > v_l * v_l + 2.0 * brake_mps2 * np.maximum(free, 0.0) * (1 + TOL) + TOL
            )
            overlap = has & (free < -TOL)
            bad = (has | (lead == STOP)) & (cannot_stop | overlap) & (gen | (has & gen[j]))
            if not bad.any():
                break
            f = int(np.flatnonzero(bad)[0])
            victim = on[f] if gen[f] else on[j[f]]
            comp.valid[s, victim] = comp.generated[s, victim] = False
            dropped[s] += 1
    return dropped

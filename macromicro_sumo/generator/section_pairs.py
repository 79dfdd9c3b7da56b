"""Stage I's speeds for a completed scene's pairs, and its last check of them.

``safe_speeds`` gives the generated vehicles speeds their pairs along the network's lanes
(``section_leaders``) can drive. ``drop_unsafe_pairs`` is the last check: a pair with a
generated vehicle in it that overlaps or whose follower cannot stop behind its leader
loses its generated vehicle (the follower where it is generated, else the leader),
counted in ``SectionCompletion.dropped`` as a vehicle that fits nowhere is.

Before the gaps followed the lane connections (``section_lanes``), it dropped 0.1-1% of the
generated vehicles on drawn nets 501 / 503 and game/cross: where the through lane changes
index at a junction (501: lane 1 of a two-lane edge onto lane 0 of a one-lane edge) the
gaps, one per SUMO lane index, put a car 0.6 m behind another across it, or 6.5 m ahead of
an observed car at 21 m/s with a slow car ahead. What it still drops are chains of
generated vehicles whose dealt-out speeds an observed follower cannot stop behind
(docs/sections-log.md, stop 34).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from macromicro_sumo.road.leaders import section_ahead, section_leaders
from macromicro_sumo.road.section import STOP, Section

TOL = 1e-6


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
    dropped: np.ndarray | None = None  # (S,) vehicles not placed: no gap had room
    wall_s: float = 0.0


def drop_unsafe_pairs(
    comp: SectionCompletion,
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
            lead, spacing, line = pair_leaders(section, lane, arc, ex, stop_lane, stop_arc)
            has = lead >= 0
            j = np.maximum(lead, 0)
            ex_l = np.where(has, ex[j], 0.0)
            v_l = np.where(has, v[j], 0.0)
            free = spacing - standstill_m[s] - ex_l
            cannot_stop = (
                v * v + 2.0 * bt * v
                > v_l * v_l + 2.0 * brake_mps2 * np.maximum(free, 0.0) * (1 + TOL) + TOL
            )
            # A generated leader's extra length (``complete_section``: in a junction) is room
            # a moving follower needs; a standing one may stand closer (SUMO keeps it there).
            standing_ok = (v <= 0.0) & gen[j] & (free + ex_l >= -TOL)
            overlap = has & (free < -TOL) & ~standing_ok
            bad = (has | (lead == STOP)) & (cannot_stop | overlap) & (gen | (has & gen[j]))
            # Behind a vehicle across a red line the line holds too (a generated follower).
            room_line = 2.0 * brake_mps2 * np.maximum(line - standstill_m[s], 0.0)
            bad |= gen & (v * v + 2.0 * bt * v > room_line * (1 + TOL) + TOL)
            other = j
            if stop_lane is not None and (lead == STOP).any():
                # Where the line leads, the vehicle past it must not overlap either (a
                # follower standing within the standstill spacing of the line).
                other, in_past = _overlaps_past(section, lane, arc, v, gen, ex, standstill_m[s])
                in_past &= (lead == STOP) & (gen | gen[other])
                bad |= in_past
                other = np.where(in_past, other, j)
            if not bad.any():
                break
            f = int(np.flatnonzero(bad)[0])
            victim = on[f] if gen[f] else on[other[f]]
            comp.valid[s, victim] = comp.generated[s, victim] = False
            dropped[s] += 1
    return dropped


def safe_speeds(
    comp: SectionCompletion,
    section: Section,
    standstill_m: np.ndarray,
    brake_mps2: float,
    reaction_s: float = 0.0,
    extra_m: np.ndarray | None = None,
    stops: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Give each generated vehicle a speed it can stop from behind its leader, and raise
    a generated leader where an observed follower could not stop behind it (in place).

    The spacing and speed bounds say nothing about pairs: a generated vehicle 15 m/s faster
    than a leader 10 m behind satisfies both and crashes in the first second. The bound is
    the stopping-distance condition v^2 <= v_leader^2 + 2 b (spacing - standstill spacing),
    with b the action bound's braking and the standstill spacing psi's smallest spacing;
    with a reaction time tau the follower first drives on for tau, v^2 + 2 b tau v <= ...
    (SUMO's safe speed in the environment, tau = one step: without it, 75 of the 123
    observed vehicles that SUMO held back on the Bremen example were held back in the
    first step, behind a generated leader). A generated vehicle must also be able to stop before the end of a lane that leads
    nowhere. The generated speeds are kept as a set and dealt out again: walking the
    vehicles downstream to upstream (a leader is served first), each gets the speed left
    in the set nearest its own that it can stop from, and only where none is left is the
    slowest one capped. Then, upstream to downstream, a generated leader is raised where
    its follower could not stop behind it (an observed follower keeps its record), and
    so on along the chain, as far as its own leader allows. Capping every offender instead
    lowered the scene's mean speed by
    1.7 m/s on the Bremen example (a quarter of the generated vehicles, 5.8 m/s each),
    and every method's rollouts inherited that error. ``stops``: (S, P) (lane, arc; NaN
    arc: none) of each scene's red or yellow stop lines (``SectionSnapshots.stop_lane``),
    standing leaders there, ordered against the tails of the vehicles past them as in the
    envs' observation (``pair_leaders``).
    """
    for s in range(len(comp.speed_mps)):
        on = np.flatnonzero(comp.valid[s])
        if on.size < 2:
            continue
        lane, arc = comp.lane[s, on], comp.arc_m[s, on]
        v, gen = comp.speed_mps[s, on].copy(), comp.generated[s, on]
        pool = np.sort(v[gen])
        # A long leader (a truck) stands its own extra length further back.
        ex = np.zeros(on.size) if extra_m is None else extra_m[s, on]
        # Along the lane connections; a lane's end is a standing leader (STOP, < 0).
        leader, spacing, line = pair_leaders(section, lane, arc, ex, *_stops_of(stops, s))
        ex_l = np.where(leader >= 0, ex[np.maximum(leader, 0)], 0.0)
        room = 2.0 * brake_mps2 * np.maximum(0.0, spacing - standstill_m[s] - ex_l)
        bt = brake_mps2 * reaction_s
        # The red line a vehicle across it hides: its cap holds beside the vehicle's.
        line_cap = np.sqrt(bt * bt + 2.0 * brake_mps2 * np.maximum(0.0, line - standstill_m[s]))
        line_cap -= bt

        # Front first: a leader (on this lane or the one it continues onto) is served first.
        for i in np.argsort(-arc, kind="stable"):
            if gen[i]:
                c = min(_cap(leader[i], v, room[i], bt), line_cap[i])
                k = _nearest_below(pool, v[i], c)
                v[i] = min(pool[k], c)
                pool = np.delete(pool, k)
        # A follower that cannot stop behind a generated leader raises it (an observed one,
        # and a generated one raised so), along whole chains of them, never beyond what
        # lets the raised one stop behind its own leader (that wins: the observed follower
        # then brakes in the environment). Back first, what each must reach: the speed its
        # follower needs once raised itself; then front first, each raised as far as its
        # own leader, raised already, allows. One pass back to front instead capped a
        # vehicle at its leader's speed before that leader was raised: on drawn 503 chains
        # of generated cars ahead of a fast observed one stayed too slow for it, and the
        # pair check dropped them (146 of 6,305 in the evaluation's scenes).
        want = v.copy()
        for i in np.argsort(arc, kind="stable"):
            j = leader[i]
            if j >= 0 and gen[j]:
                need = math.sqrt(max(0.0, want[i] ** 2 + 2.0 * bt * want[i] - room[i]))
                want[j] = max(want[j], need)
        for j in np.argsort(-arc, kind="stable"):
            if gen[j] and want[j] > v[j]:
                v[j] = max(v[j], min(want[j], _cap(leader[j], v, room[j], bt), line_cap[j]))
        comp.speed_mps[s, on] = v


def pair_leaders(
    section: Section,
    lane: np.ndarray,
    arc_m: np.ndarray,
    extra_m: np.ndarray,
    stop_lane: np.ndarray | None,
    stop_arc_m: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leader (``STOP``: a stop line or lane end, -1: none) and front-to-front spacing of
    each vehicle of a scene, and the spacing to the stop line a vehicle standing across it
    hides (inf: none).

    The one leader search (``road.leaders.section_ahead``) with the vehicles' extra lengths
    (``extra_m``, beyond the snapshots' shortest) orders a stop line against the tails of the
    vehicles past it, as the envs' observation and the deployment do: a truck 12 m long whose
    front stands 3 m past a red line leads its follower, its tail 9 m before the line (by
    fronts the line led and the pair check allowed the follower up to 7 m nearer the truck's
    tail than psi's standstill spacing, stop 49). With minGap and jmStoplineGap 0, a vehicle
    past the line is the leader where the pair check's free room to it (spacing - standstill
    - its extra) is no more than to the line (distance - standstill, a shortest vehicle's
    front at the line). The line still holds for the follower (SUMO stops there at red
    whatever moves ahead): ``line``, from the search by fronts, where the two differ."""
    lead, spacing, _ = section_ahead(
        section, lane, arc_m, stop_lane, stop_arc_m, None, extra_m, 0.0, 0.0
    )
    line = np.full(len(arc_m), np.inf)
    # Only a vehicle longer than the shortest can hide a line (none: the search by fronts).
    if stop_lane is not None and len(stop_lane) and (lead >= 0).any() and (extra_m > 0).any():
        front, by_front = section_leaders(section, lane, arc_m, stop_lane, stop_arc_m)
        hid = (front == STOP) & (lead >= 0)
        line[hid] = by_front[hid]
    return lead, spacing, line


def _overlaps_past(
    section: Section,
    lane: np.ndarray,
    arc: np.ndarray,
    v: np.ndarray,
    gen: np.ndarray,
    ex: np.ndarray,
    standstill_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The next vehicle along the lane connections, stop lines aside (index, 0: none), and
    where a vehicle overlaps it (``drop_unsafe_pairs``' overlap: a standing follower may
    stand a generated leader's extra length closer)."""
    car, spacing = section_leaders(section, lane, arc)
    k = np.maximum(car, 0)
    free = spacing - standstill_m - ex[k]
    standing_ok = (v <= 0.0) & gen[k] & (free + ex[k] >= -TOL)
    return k, (car >= 0) & (free < -TOL) & ~standing_ok


def _stops_of(
    stops: tuple[np.ndarray, np.ndarray] | None, s: int | np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Scene(s) ``s``'s stop lines (lane, arc), their padding dropped (one scene)."""
    if stops is None:
        return None, None
    ok = np.isfinite(stops[1][s])
    return stops[0][s][ok], stops[1][s][ok]


def _cap(j: int, v: np.ndarray, room: float, bt: float) -> float:
    """The most a vehicle with leader ``j`` (``STOP``: a lane end, -1: none) can drive and
    still stop behind it: v^2 + 2 bt v <= v_j^2 + room."""
    if j == STOP:
        return math.sqrt(bt * bt + room) - bt
    if j >= 0:
        return math.sqrt(bt * bt + v[j] ** 2 + room) - bt
    return math.inf


def _nearest_below(pool: np.ndarray, v: float, cap: float) -> int:
    """Index of the sorted ``pool``'s value nearest ``v`` among those <= ``cap`` (the
    smallest value's, 0, where none is)."""
    hi = int(np.searchsorted(pool, cap, side="right"))  # pool[:hi] <= cap
    if hi == 0:
        return 0
    k = min(int(np.searchsorted(pool, v)), hi - 1)
    if k > 0 and abs(pool[k - 1] - v) <= abs(pool[k] - v):
        k -= 1
    return k

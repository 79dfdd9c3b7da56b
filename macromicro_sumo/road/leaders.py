"""Who is ahead on a section: leaders along the lane connections and standing obstacles.

``lane_leaders`` (per lane index) and ``section_leaders`` (along the network's lane
connections, with a lane's end and a red light's stop line as standing leaders, ``STOP``);
``standing_spacing_m``, ``nearer_standing`` and ``stop_distance_m``: where SUMO's drivers
stop before such an obstacle, and the spacing a standing leader is observed at;
``bumper_gap_m`` and ``set_leader_gap``: the gap layouts' leader column from the spacing.
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.road.physics import LEADER_COLUMN, observes_gap
from macromicro_sumo.road.ring import loop_successors
from macromicro_sumo.road.section import NO_LEADER_GAP_M, STOP, Section

# SUMO's defaults where a vType sets neither, for every carFollowModel (SUMO 1.28, measured:
# Krauss, IDM, EIDM, ACC, CACC, W99 ... stop 1.00-1.07 m before a red line): its drivers
# stop jmStoplineGap before a red line, and minGap behind a vehicle (a passenger car's).
STOPLINE_GAP_M = 1.0
STANDING_MIN_GAP_M = 2.5
# What ``section_ahead`` found ahead of a vehicle: nothing, a vehicle, a stop point given
# (a red or yellow light's stop line), the end of a lane (a standing obstacle, ``STOP``).
AHEAD_NONE, AHEAD_VEHICLE, AHEAD_RED, AHEAD_END = 0, 1, 2, 3


def lane_leaders(
    lane: np.ndarray, arc_m: np.ndarray, length_m: float, closed: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Leader index (-1: none) and front-to-front spacing [m] of every vehicle, per lane.

    O(V log V) for V vehicles: one sort by (lane, arc). On an open section the first
    vehicle of a lane has no leader (spacing ``NO_LEADER_GAP_M``); on a closed one it
    follows the last vehicle of its lane around the loop.
    """
    v = len(arc_m)
    leader = np.full(v, -1, dtype=np.int64)
    spacing = np.full(v, NO_LEADER_GAP_M)
    if v == 0:
        return leader, spacing
    order = np.lexsort((arc_m, lane))
    ln, s = lane[order], arc_m[order]
    same = ln[1:] == ln[:-1]
    behind, ahead = order[:-1][same], order[1:][same]
    leader[behind] = ahead
    spacing[behind] = (s[1:] - s[:-1])[same]
    if closed:
        # Last vehicle of each lane follows that lane's first vehicle, around the loop.
        first = np.concatenate([[True], ~same])
        last = np.concatenate([~same, [True]])
        firsts, lasts = order[first], order[last]
        leader[lasts] = firsts
        spacing[lasts] = s[first] + length_m - s[last]
        alone = firsts == lasts
        spacing[lasts[alone]] = length_m
    return leader, spacing


def section_leaders(
    section: Section,
    lane: np.ndarray,
    arc_m: np.ndarray,
    stop_lane: np.ndarray | None = None,
    stop_arc_m: np.ndarray | None = None,
    on_route: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Leader index and front-to-front spacing [m] of every vehicle along the network's
    lane connections: ``section_ahead`` without the kinds."""
    leader, spacing, _ = section_ahead(section, lane, arc_m, stop_lane, stop_arc_m, on_route)
    return leader, spacing


def section_ahead(
    section: Section,
    lane: np.ndarray,
    arc_m: np.ndarray,
    stop_lane: np.ndarray | None = None,
    stop_arc_m: np.ndarray | None = None,
    on_route: np.ndarray | None = None,
    length_m: np.ndarray | None = None,
    min_gap_m: float | np.ndarray = STANDING_MIN_GAP_M,
    stopline_gap_m: float | np.ndarray = STOPLINE_GAP_M,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leader index, front-to-front spacing [m] and the kind of what is ahead (``AHEAD_*``)
    of every vehicle along the network's lane connections (what a driver on that lane meets
    next), not along lane indices.

    Where a lane is added on the right (an on-ramp), the through lanes' indices shift by
    one at the edge boundary: a leader looked up by index would be a vehicle on another
    lane. Leader -1: none on the section (spacing ``NO_LEADER_GAP_M``); ``STOP``: a
    standing obstacle, at the end of a lane that leads nowhere (``Section.lane_ends``), for
    the vehicles ``on_route`` (V,) (None: none) at the end of any lane that does not
    continue along the section (``Section.route_ends``: a turning lane too), either at the
    end of the chain of lanes that all end (``Section.chain_beyond_m``), or at a stop
    point given by ``stop_lane`` / ``stop_arc_m`` (a red light's stop line), with the
    spacing to it. The kind says which: ``AHEAD_RED`` a stop point given, ``AHEAD_END`` a
    lane's end (a driver stops 1 m before the one, at the other: ``standing_spacing_m``).
    With the vehicles' ``length_m`` (V,), a stop point is ordered against the tails of the
    vehicles past it (``_across_the_line``): a vehicle standing across a red line leads its
    follower where SUMO's gap to it is less than to the line, with the follower's own
    ``min_gap_m`` and ``stopline_gap_m`` (jmStoplineGap) (scalars or (V,)).
    O(V log V): one sort by (lane of an edge, arc), then one pass over the section's lanes.
    """
    v = len(arc_m)
    leader = np.full(v, -1, dtype=np.int64)
    spacing = np.full(v, NO_LEADER_GAP_M)
    if v == 0:
        return leader, spacing, np.zeros(0, dtype=np.int8)
    lane = np.asarray(lane, dtype=np.int64)
    arc = np.asarray(arc_m, dtype=float)
    if stop_lane is not None and stop_arc_m is not None and len(stop_arc_m):
        lane = np.concatenate([lane, np.asarray(stop_lane, dtype=np.int64)])
        arc = np.concatenate([arc, np.asarray(stop_arc_m, dtype=float)])
    if section.closed and section.max_lanes == 1 and section.links.all():
        nxt, gap = loop_successors(np.mod(arc, section.length_m), section.length_m)
        if length_m is not None and len(arc) > v:
            _across_the_line(nxt, gap, v, length_m, min_gap_m, stopline_gap_m)
        nxt, gap = nxt[:v], gap[:v]
        return np.where(nxt >= v, STOP, nxt), gap, _kinds(nxt, v)
    m = section.max_lanes
    edge, rel = section.node_of(arc)
    node = edge * m + np.clip(lane, 0, section.n_lanes[edge] - 1)
    order = np.lexsort((rel, node))
    nd, r = node[order], rel[order]
    same = nd[1:] == nd[:-1]
    nxt = np.full(len(arc), -1, dtype=np.int64)
    gap = np.full(len(arc), NO_LEADER_GAP_M)
    nxt[order[:-1][same]] = order[1:][same]
    gap[order[:-1][same]] = (r[1:] - r[:-1])[same]
    first = np.concatenate([[True], ~same])
    last = np.concatenate([~same, [True]])
    first_idx = np.full(len(section.edge_ids) * m, -1, dtype=np.int64)
    first_rel = np.full(len(section.edge_ids) * m, np.inf)
    first_idx[nd[first]], first_rel[nd[first]] = order[first], r[first]
    ahead, off = section.ahead_of_lanes(first_idx, first_rel)
    lasts, ln = order[last], nd[last]
    to_end = section.node_span_m[edge[lasts]] - rel[lasts]
    found = ahead[ln] >= 0
    nxt[lasts[found]] = ahead[ln[found]]
    gap[lasts[found]] = (to_end + off[ln])[found]
    # The end of the lane, or of the chain of lanes it leads onto that all end.
    everyone, driven = section.end_beyond_m
    beyond = everyone.ravel()[ln]
    if on_route is not None:  # stop points (index >= v) are no vehicle: their ends unread
        route = np.concatenate([np.asarray(on_route, dtype=bool), np.zeros(len(arc) - v, bool)])
        beyond = np.where(route[lasts], driven.ravel()[ln], beyond)
    ends = ~found & np.isfinite(beyond)
    nxt[lasts[ends]] = STOP
    gap[lasts[ends]] = (to_end + beyond)[ends]
    if length_m is not None and len(arc) > v:
        walk = (section.node_span_m, edge, rel, node, off)
        _across_the_line(nxt, gap, v, length_m, min_gap_m, stopline_gap_m, walk)
    nxt, gap = nxt[:v], gap[:v]
    leader[:] = np.where(nxt >= v, STOP, nxt)
    spacing[:] = np.where(nxt == -1, NO_LEADER_GAP_M, gap)
    return leader, spacing, _kinds(nxt, v)


def _across_the_line(
    nxt: np.ndarray,
    gap: np.ndarray,
    v: int,
    length_m: np.ndarray,
    min_gap_m: float | np.ndarray,
    stopline_gap_m: float | np.ndarray,
    walk: tuple[np.ndarray, ...] | None = None,
) -> None:
    """Order the stop points (items >= ``v`` of the successors ``nxt`` and the arcs ``gap``
    to them, changed in place) against the tails of the vehicles past them: the sort puts a
    stop point at its line and a vehicle at its front, so a vehicle whose front is past a
    red line but whose tail is not (or less than minGap - jmStoplineGap past it) hid behind
    the line from whoever followed it (drawn arterial 1701: a follower braked for the line
    17.6 m ahead into a tail 8.4 m ahead, stop 48). A vehicle whose successor is a stop
    point takes the first vehicle past it (through further stop points) where the line is
    not nearer as the deployment compares SUMO's leader with its stop (``nearer_standing``:
    the line's standing spacing, shifted to the leader's length, against the spacing to the
    leader). ``walk`` (the open walk's nodes' spans, per item its edge, arc in its node and
    node, per node the offset to what is met downstream): the spacing is then taken as the search
    without stop points takes it, to the bit, where one stop point lies between."""
    f = np.flatnonzero(nxt[:v] >= v)
    if not f.size:
        return
    p = nxt[f]
    car, past = nxt[p], gap[p]  # what lies past the line, the arc from the line to it
    hops = None
    if (car >= v).any():  # two red lines within a vehicle's length: rare
        hops = np.zeros(f.size, dtype=np.int64)
        for _ in range(len(nxt) - v):
            more = np.flatnonzero(car >= v)
            if not more.size:
                break
            past[more] += gap[car[more]]
            car[more] = nxt[car[more]]
            hops[more] += 1
    # Only a vehicle whose tail is less than minGap - min(jmStoplineGap, 0) past the line
    # can be nearer than it (SUMO's gap to it, past - its length - minGap, against the
    # line's, distance - jmStoplineGap or 0): most followers of a line are done here (0.01 m
    # spare for the sums' last bits).
    reach = np.max(min_gap_m) - min(float(np.min(stopline_gap_m)), 0.0) + 0.01
    ok = car >= 0
    ok &= past - length_m[np.where(ok, car, 0)] < reach
    if not ok.any():
        return
    f, p, car = f[ok], p[ok], car[ok]
    line = gap[f]
    spacing = line + past[ok]
    if walk is not None:
        span, edge, rel, node, off = walk
        nd = node[f]
        # In the follower's node (past an open section's last edge end): the arcs' difference.
        same = node[car] == nd
        # The line its node's last, the vehicle the one met downstream of that node: the arc
        # to the node's end plus the node's offset to it.
        beyond = ~same & (node[p] == nd)
        if hops is not None:
            beyond &= hops[ok] == 0
        spacing = np.where(same, rel[car] - rel[f], spacing)
        spacing = np.where(beyond, (span[edge[f]] - rel[f]) + off[nd], spacing)
    own = length_m[f]
    mg = min_gap_m if np.ndim(min_gap_m) == 0 else np.asarray(min_gap_m)[f]
    sg = stopline_gap_m if np.ndim(stopline_gap_m) == 0 else np.asarray(stopline_gap_m)[f]
    standing = standing_spacing_m(line, own, sg, mg)
    # The line is nearer where its standing spacing, shifted to the leader's length, is less.
    take = ~(standing + length_m[car] - own < spacing)
    nxt[f[take]] = car[take]
    gap[f[take]] = spacing[take]


def _kinds(nxt: np.ndarray, v: int) -> np.ndarray:
    """``AHEAD_*`` of successors ``nxt`` (-1: none, ``STOP``: a lane's end, >= ``v``: a
    stop point given, else a vehicle)."""
    kind = np.where(nxt >= 0, AHEAD_VEHICLE, AHEAD_NONE).astype(np.int8)
    kind[nxt >= v] = AHEAD_RED
    kind[nxt == STOP] = AHEAD_END
    return kind


def standing_spacing_m(
    dist_m: np.ndarray,
    length_m: np.ndarray,
    stop_gap_m: float | np.ndarray = 0.0,
    min_gap_m: float | np.ndarray = STANDING_MIN_GAP_M,
) -> np.ndarray:
    """Front-to-front spacing a vehicle ``length_m`` long observes to a standing obstacle
    ``dist_m`` ahead of its front: a standing vehicle of its length ``min_gap_m`` (its own
    minGap; SUMO's default ``STANDING_MIN_GAP_M``) beyond where SUMO's driver stops,
    ``stop_gap_m`` before it (a red line: its jmStoplineGap, SUMO's default
    ``STOPLINE_GAP_M``; a lane end: 0): SUMO's gap to a red light is distance -
    jmStoplineGap, to a vehicle distance - minGap, and readers take gap = spacing - length
    - minGap. The envs', demand env's and deployment's one definition. A ``stop_gap_m`` of
    0.0 is not subtracted (x - 0.0 is x, -0.0 included): one array call less a step."""
    stop = dist_m if isinstance(stop_gap_m, float) and stop_gap_m == 0.0 else dist_m - stop_gap_m
    return np.maximum(stop, 0.0) + min_gap_m + length_m


def nearer_standing(
    spacing_m: np.ndarray,
    stop_m: np.ndarray,
    length_m: np.ndarray,
    min_gap_m: float | np.ndarray = STANDING_MIN_GAP_M,
    leader_length_m: np.ndarray | None = None,
) -> np.ndarray:
    """Where a standing obstacle ``stop_m`` (``stop_distance_m``, inf: none) is nearer than the
    leader, ``spacing_m`` becomes ``standing_spacing_m`` (in place) with the vehicles' own
    ``min_gap_m``; the mask of those. ``leader_length_m``: the leaders' lengths in
    ``spacing_m`` (None: the own, ``length_m``; a vehicle without a leader, spacing
    ``NO_LEADER_GAP_M``, takes its own): nearer is then SUMO's gap to the stop against
    SUMO's gap to the leader. Compared as spacings, a standing obstacle of the own length,
    a truck (12 m) took a car (5 m) that stood or moved less than 7 m past its stop as
    nearer than a red line and crept to the line (arterial 521, stop 40)."""
    standing = standing_spacing_m(np.asarray(stop_m, dtype=float), length_m, 0.0, min_gap_m)
    if leader_length_m is None:
        closer = standing < spacing_m
    else:
        led = np.asarray(spacing_m) < NO_LEADER_GAP_M
        closer = standing + np.where(led, leader_length_m - length_m, 0.0) < spacing_m
    np.copyto(spacing_m, standing, where=closer)
    return closer


def stop_distance_m(
    lane_end_m: np.ndarray,
    red_m: np.ndarray,
    stopline_gap_m: float | np.ndarray = STOPLINE_GAP_M,
) -> np.ndarray:
    """SUMO's gap to a stop: a lane end's distance, or a red line's less the vehicles'
    jmStoplineGap ``stopline_gap_m`` (SUMO's default ``STOPLINE_GAP_M``)."""
    red = np.maximum(np.asarray(red_m, dtype=float) - stopline_gap_m, 0.0)  # NaN stays
    return np.fmin(np.asarray(lane_end_m, dtype=float), red)


def bumper_gap_m(spacing_m: np.ndarray, leader_length_m: np.ndarray | float) -> np.ndarray:
    """The bumper-to-bumper gap [m] (the leader's rear minus the own front) of a front-to-
    front ``spacing_m``: spacing - the leader's length. A standing obstacle's leader length
    is the vehicle's own (``standing_spacing_m`` stands a vehicle of its length there), so
    its gap is SUMO's gap to where the driver stops plus its minGap, as behind a vehicle,
    where SUMO stops it minGap behind the rear. No leader (``NO_LEADER_GAP_M`` or farther)
    keeps ``NO_LEADER_GAP_M``. The envs', demand env's and deployment's one definition."""
    spacing = np.asarray(spacing_m, dtype=float)
    return np.where(spacing < NO_LEADER_GAP_M, spacing - leader_length_m, NO_LEADER_GAP_M)


def set_leader_gap(
    obs: np.ndarray, observation: str, leader_length_m: np.ndarray | None
) -> np.ndarray:
    """Where ``policy.observation``'s leader column is the gap (``physics.observes_gap``),
    make ``obs``' (..., F) column of front-to-front spacings the bumper gap (in place) with
    each row's ``leader_length_m`` (...,): the leader vehicle's length, the own length for
    a standing obstacle, any value where there is no leader (``bumper_gap_m``). Other
    layouts are left as they are (``leader_length_m`` may then be None); returns ``obs``."""
    if observes_gap(observation):
        if leader_length_m is None:
            raise ValueError(f"policy.observation = {observation!r} needs the leaders' lengths")
        obs[..., LEADER_COLUMN] = bumper_gap_m(obs[..., LEADER_COLUMN], leader_length_m)
    return obs

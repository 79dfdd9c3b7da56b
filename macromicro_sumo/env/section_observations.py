"""What a vehicle observes on a section (Stage II's envs, the micro pairs, the demand env).

``section_observations``: the observations, leaders and spacings of the active vehicles
(leaders along the lane connections, standing obstacles as standing leaders);
``stop_points``: the red lines ahead of vehicles as stop points on the section's arc;
``initial_observations``: every vehicle's observation at every episode's start, what the
policy's input normalisation is fitted on.
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.road.leaders import (
    AHEAD_RED,
    STANDING_MIN_GAP_M,
    STOPLINE_GAP_M,
    section_ahead,
    set_leader_gap,
    standing_spacing_m,
)
from macromicro_sumo.road.physics import OBSERVATION_FEATURES, observes_gap, set_own_features
from macromicro_sumo.road.section import NO_LEADER_GAP_M, STOP, Section


def section_observations(
    section: Section,
    lane: np.ndarray,
    arc_m: np.ndarray,
    speed_mps: np.ndarray,
    active: np.ndarray,
    observation: str,
    stop_lane: np.ndarray | None = None,
    stop_arc_m: np.ndarray | None = None,
    factor: np.ndarray | None = None,
    length_m: np.ndarray | None = None,
    on_route: np.ndarray | None = None,
    min_gap_m: np.ndarray | None = None,
    stopline_gap_m: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations (N, obs_dim), leader (-1: none, ``STOP``: a standing obstacle) and
    spacing of the active vehicles; ``factor`` (N,): each driver's desired-speed factor,
    which multiplies the limits it observes (``env.driver_speed``; None: 1); ``length_m``
    (N,): each vehicle's length, for an observation with own features (``physics.
    set_own_features``) and the spacing to a standing leader (``road.leaders.
    standing_spacing_m``; None: the distance alone), with each vehicle's own vType's
    ``min_gap_m`` and ``stopline_gap_m`` (jmStoplineGap) (N,) (None: SUMO's defaults).
    A gap layout (``physics.observes_gap``) needs ``length_m``: its leader column is the
    spacing less the leader's length, a standing leader's the own (``road.leaders.
    bumper_gap_m``); ``spacing`` stays front to front.

    Leaders along the lane connections (``section_ahead``, one sort per call); the end
    of a lane that leads nowhere, for the vehicles ``on_route`` (N,) (the driven ones,
    which drive the section's route; None: none) that of any lane that does not continue
    along the section (``Section.route_ends``: a turning lane), and the stop points given
    (red lights) are standing leaders, as a driver sees them (in ``leader``: ``STOP``;
    which of them ``section_ahead`` says: a stop point found takes the stop line's gap). The
    observation sees no leader (``NO_LEADER_GAP_M``, delta v 0) at that spacing or beyond,
    as the deployment does; ``leader`` and ``spacing`` keep it. Inactive slots get zeros
    and no leader.
    """
    n = len(arc_m)
    if length_m is None and observes_gap(observation):
        raise ValueError(f"policy.observation = {observation!r} needs each vehicle's length")
    obs = np.zeros((n, len(OBSERVATION_FEATURES[observation])))
    leader = np.full(n, -1, dtype=np.int64)
    spacing = np.full(n, NO_LEADER_GAP_M)
    idx = np.flatnonzero(active)
    if idx.size == 0:
        return obs, leader, spacing
    ln, s, v = lane[idx], arc_m[idx], speed_mps[idx]
    route = None if on_route is None else on_route[idx]
    own = None if length_m is None else length_m[idx]
    stop_gap = STOPLINE_GAP_M if stopline_gap_m is None else stopline_gap_m[idx]
    min_gap = STANDING_MIN_GAP_M if min_gap_m is None else min_gap_m[idx]
    # With the lengths, a vehicle standing across a red line leads its follower where SUMO's
    # gap to it is less than to the line (the stop points ordered against the tails).
    lead, gap, kind = section_ahead(
        section, ln, s, stop_lane, stop_arc_m, route, own, min_gap, stop_gap
    )
    standing = lead == STOP
    if own is not None and standing.any():
        red = kind == AHEAD_RED  # a stop point given (a red line); else a lane's end
        gap = np.where(standing, standing_spacing_m(gap, own, stop_gap * red, min_gap), gap)
    has = lead >= 0
    leader[idx[has]] = idx[lead[has]]
    leader[idx[standing]] = STOP  # readers take >= 0 as a vehicle; the code says which
    spacing[idx] = gap
    e = section.edge_index(s)
    lim = section.limits_mps
    o = obs[idx]
    o[:, 0] = v
    o[:, 1] = lim[e, np.minimum(ln, section.n_lanes[e] - 1)]
    # A leader as far as NO_LEADER_GAP_M or farther is none, as the deployment's look-ahead
    # (SUMO's getLeader within it) and the demand env's see it.
    near = gap < NO_LEADER_GAP_M
    o[:, 2] = np.where(near, gap, NO_LEADER_GAP_M)
    dv = np.where(has, v - v[np.maximum(lead, 0)], np.where(standing, v, 0.0))
    o[:, 3] = np.where(near, dv, 0.0)
    if o.shape[1] > 4:
        o[:, 4], o[:, 5] = section.lookahead(ln, s, e, o[:, 1])
    if factor is not None:
        o[:, 1] *= factor[idx]
        if o.shape[1] > 4:
            o[:, 4] *= factor[idx]
    set_own_features(o, observation, own)
    if observes_gap(observation):  # the leader's length; a standing leader's is the own
        set_leader_gap(o, observation, np.where(has, own[np.maximum(lead, 0)], own))
    obs[idx] = o
    return obs, leader, spacing


def stop_points(
    section: Section,
    lane: np.ndarray,
    arc_m: np.ndarray,
    dist_m: np.ndarray,
    link_lanes: list[str] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(lane, arc) of the stop lines ``dist_m`` ahead of vehicles at (``lane``, ``arc_m``)
    (inf: none), one per distinct place.

    A stop line is the end of an edge: the distance SUMO gives is along the vehicle's own
    lane, whose length can differ from the section's arc of that edge (a curve), so each
    point is snapped to the edge end nearest that distance ahead; the spacing observed is
    then the arc to it. The point lies on the lane the vehicle reaches there along the
    lane connections (``lane_reached``), not on its own lane index: past an on-ramp the
    through lanes' indices shift. Where ``link_lanes`` gives the lane of the red link
    (``Simulation.stop_lines``) on that edge, the point lies on it: on game/cross a car
    routed through on 1si's right-turn lane sees the through link's red, which would
    otherwise stop the right turners behind it at a green light. Lines past an open
    section's end are dropped.
    """
    ok = np.isfinite(dist_m)
    if not ok.any():
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    ln, s, d = np.asarray(lane)[ok], np.asarray(arc_m, dtype=float)[ok], dist_m[ok]
    ends = section.offsets_m + section.lengths_m
    ahead = section.wrap(ends[None, :] - s[:, None])
    ahead = np.where(ahead >= 0.0, ahead, np.inf)
    end = np.argmin(np.abs(ahead - d[:, None]), axis=1)
    best = ahead[np.arange(len(s)), end]
    keep = np.isfinite(best)
    arc = section.wrap(s[keep] + best[keep])
    at = lane_reached(section, section.node_of(s[keep])[0], ln[keep], end[keep])
    if link_lanes is not None:  # SUMO's own lane of the red link, on the edge it ends
        own = [section.lanes.get(x) for x in np.asarray(link_lanes, dtype=object)[ok][keep]]
        for j, (got, e) in enumerate(zip(own, end[keep], strict=True)):
            if got is not None and got[0] == int(e):
                at[j] = got[1]
    pts = np.unique(np.stack([at.astype(float), np.round(arc, 6)], axis=1), axis=0)
    return pts[:, 0].astype(np.int64), pts[:, 1]


def lane_reached(
    section: Section, edge: np.ndarray, lane: np.ndarray, to_edge: np.ndarray
) -> np.ndarray:
    """The lane index on ``to_edge`` (at or after ``edge``) that ``lane`` of ``edge`` leads
    onto along the connections: where a lane continues onto several, the rightmost that
    carries on along the section (not a ``Section.route_ends`` lane, a turning lane), else
    the rightmost; a lane continuing nowhere keeps its index (clipped)."""
    n = len(section.edge_ids)
    e = np.asarray(edge, dtype=np.int64).copy()
    ln = np.minimum(np.asarray(lane, dtype=np.int64), section.n_lanes[e] - 1)
    for _ in range(n):
        go = np.flatnonzero(e != to_edge)
        if not go.size:
            break
        row = section.links[e[go], ln[go]]
        k = (e[go] + 1) % n
        through = row & ~section.route_ends[k]
        pick = np.where(through.any(-1), through.argmax(-1), row.argmax(-1))
        ln[go] = np.where(row.any(-1), pick, np.minimum(ln[go], section.n_lanes[k] - 1))
        e[go] = k
    return ln


def initial_observations(sc, section: Section, bank: SectionBank) -> np.ndarray:
    """Every valid vehicle's observation at the start of every episode, (V, obs_dim).

    What the policy's input normalisation is fitted on (no SUMO run needed).
    """
    rows = []
    runs: dict[int, Section] = {}  # one section per run: its speed limits
    for ep in range(len(bank)):
        valid = bank.valid[ep]
        run = int(bank.run[ep])
        if run not in runs:
            runs[run] = bank.section_of(section, ep)
        obs, _, _ = section_observations(
            runs[run],
            bank.lane0[ep],
            section.wrap(bank.arc0_m[ep]),
            bank.speed0_mps[ep],
            valid,
            sc.policy.observation,
            length_m=bank.length_m[ep],
            **bank.gaps_of(ep),
        )
        rows.append(obs[valid])
    return np.concatenate(rows) if rows else np.zeros((0, 4))

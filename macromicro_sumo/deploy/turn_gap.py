"""A commanded vehicle that must change lanes for its route slows for a gap on its target lane
as SUMO's lane changer (LC2013) slows its own drivers (``deploy.turn_gap = "sumo"``,
``turn_gap_caps``).

LC2013 makes a change for the route urgent from its usable distance (the distance left less
the occupation of the lane it must reach, ``deploy.lane_change``) and, while the change is
blocked, asks its vehicle for less speed (``MSLCM_LC2013::patchSpeed``: behind the target
lane's leader, so that it falls back to a gap). A speed command overrides that request, so
a commanded turner drove on beside a queue on its turn lane and, handed to SUMO at the plain
reach (``deploy.merge``) when the queue already stood beside it, stood at the stop line on
the wrong lane through the green: on drawn arterial 565 35% of the policy's squared speed
error sat at one station before the last signal (docs/deploy-log.md, stop 44, hD44).
``getSpeedWithoutTraCI`` holds the speed SUMO's own model chose, the changer's request
included, and so does the blocking follower's (LC2013 asks it to cooperate). Both are
asked only of vehicles on a junction edge's lanes (a connection off the section, where a
turner changes: ``junction_lanes``) whose saved lane-change state says an urgent change for
the route is blocked (``sumo.simulation.Simulation.blocked_changes``); a section without a
junction edge (netgen_corridor, Bremen) and a one-lane road ask nothing.

The default since stop 45 (hT45). All 4 runs, policy, off -> sumo, speed RMSE: drawn
arterials 565 1.178 -> 0.773 m/s, 837 1.171 -> 0.896, 615 1.408 -> 0.938, 917 0.927 ->
0.783 (runs 0-1 of 917 +0.03 / +0.10); the stalled lane-1 greens at 565's j3 4 -> 0;
netgen_corridor and Bremen byte-equal; 0 collisions, 0 teleports (docs/deploy-log.md).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from macromicro_sumo.deploy.turns import junction_edges, turn_limits
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates

# SUMO's own speed counts as the changer's request only this far below the vehicle's speed:
# Krauss' dawdling alone is at most sigma accel dt = 0.65 m/s at SUMO's defaults (the merge
# yield's MERGE_YIELD_TOLERANCE_MPS, for the same reason).
TURN_GAP_TOLERANCE_MPS = 1.0


def gap_caps(own: np.ndarray, speed: np.ndarray, decel: np.ndarray, dt_s: float) -> np.ndarray:
    """The caps [m/s] of vehicles at ``speed`` whose lane changer asked for SUMO's own speed
    ``own`` (NaN: not asked): ``own`` where it is more than ``TURN_GAP_TOLERANCE_MPS`` below
    the speed, at least v - ``decel`` dt (``own`` was chosen from the last step's speed: a
    command that accelerated since would brake harder than the vType's decel); inf
    elsewhere."""
    asked = own < speed - TURN_GAP_TOLERANCE_MPS  # NaN: False
    return np.where(asked, np.maximum(own, speed - decel * dt_s), np.inf)


def junction_lanes(section: Section, net_file: Path) -> frozenset[str]:
    """The lanes of ``section``'s junction edges (``deploy.turns.junction_edges``: a
    connection off the section), where a turner changes lanes for its turn; no internal
    lane."""
    junction = junction_edges(section, turn_limits(net_file, section))
    return frozenset(
        lane for lane, got in section.lanes.items() if junction[got[0]] and lane[0] != ":"
    )


def drop_lanes(section: Section, on: frozenset[str]) -> frozenset[str]:
    """The lanes of ``on`` (``junction_lanes`` of ``section``) that lead nowhere
    (``Section.lane_ends``: a lane drop's ending lane), which every vehicle on them must
    leave: a lane-drop changer's, not a turner's. An exit-only lane (its links all off the
    section) is not one: its through cars change as turners do."""
    ends, table = section.lane_ends, section.lanes
    return frozenset(lane for lane in on if ends[table[lane][0], table[lane][1]])


def asked_lanes(section: Section, net_file: Path, occupation: bool) -> frozenset[str]:
    """The lanes ``turn_gap_caps`` asks on: ``junction_lanes``, less the ones that lead
    nowhere (``drop_lanes``) where the driver's ``occupation`` is on (``deploy.merge_reach``
    with merge "sumo"). Why: occupation's hand-over and yield (``deploy.merge_yield``) take
    the vehicles that must leave an ending lane, and both together held the traffic twice
    for the same merge. Drawn 1045 (4 lanes to 2 where its off-ramp leaves: lane 3 ends),
    all 4 runs, policy, occupation, speed RMSE: turn_gap off 1.647, every blocked change
    2.195, not the ending lane's changers 1.661 m/s (every run better; also skipping the
    exit-only lane 0's: the same 1.661, but drawn 549's exit-only lane 3.597 -> 3.684).
    Drawn 549 and the drawn arterials have no ending junction lane: nothing skipped (stop
    46, hM46). Read from the net once per driver."""
    on = junction_lanes(section, net_file)
    return on - drop_lanes(section, on) if occupation else on


def change_sides(
    section: Section, lanes: list[str], on: frozenset[str]
) -> tuple[list[int], list[int]]:
    """(index into ``lanes``, side -1 right / 1 left) for each side of each vehicle on a lane
    in ``on`` (``asked_lanes`` of ``section``) with a neighbour lane on that side of its
    edge."""
    at: list[int] = []
    sides: list[int] = []
    table, n_lanes = section.lanes, section.n_lanes
    for k, lane in enumerate(lanes):
        if lane not in on:
            continue
        got = table[lane]
        edge, index = got[0], got[1]
        if index > 0:
            at.append(k)
            sides.append(-1)
        if index < n_lanes[edge] - 1:
            at.append(k)
            sides.append(1)
    return at, sides


def turn_gap_caps(
    sc: SectionScenario,
    section: Section,
    shape_of: Mapping[str, tuple[float, float, float]],
    st: VehicleStates,
    rows: np.ndarray,
    cap: np.ndarray | None,
    on: frozenset[str] | None,
) -> np.ndarray | None:
    """With ``deploy.turn_gap = "sumo"``: ``cap`` (per commanded vehicle, rows ``rows`` of the
    road's state ``st``; None: none) lowered to ``gap_caps`` where SUMO asked a commanded
    vehicle for less speed for an urgent change for a route that is blocked: the changer's
    own (it falls back to a gap) and a follower's that blocks the change (it opens one, as
    LC2013 asks a SUMO driver to cooperate), any vehicle on the section's lanes the changer
    (one SUMO drives, a handed-over one, a commanded one). ``shape_of``: vehicle -> (length,
    minGap, decel); ``on``: the lanes to ask on (``asked_lanes``, read once by the driver)."""
    if sc.deploy.turn_gap != "sumo":
        return cap
    if not on or not len(rows):  # no junction edge (a motorway section): nothing asked
        return cap
    at, sides = change_sides(section, st.lanes, on)
    if not at:  # one lane everywhere: nothing asked of SUMO
        return cap
    ids = st.ids
    own, back = Simulation.blocked_changes([ids[k] for k in at], sides)
    asked: dict[str, float] = dict(back)  # the followers' own speeds
    for k, v in zip(at, own.tolist(), strict=True):
        if v == v:  # the changer's own (one side at most: a change is wanted one way)
            asked[ids[k]] = min(v, asked.get(ids[k], np.inf))
    if not asked:
        return cap
    mine = [(i, asked[ids[r]]) for i, r in enumerate(rows.tolist()) if ids[r] in asked]
    if not mine:
        return cap
    sel = np.array([i for i, _ in mine])
    decel = np.array([shape_of[ids[rows[i]]][2] for i in sel.tolist()])
    got = np.full(len(rows), np.inf)
    speed = st.speed_mps[rows[sel]]
    got[sel] = gap_caps(np.array([v for _, v in mine]), speed, decel, sc.simulation.step_length_s)
    return got if cap is None else np.minimum(cap, got)

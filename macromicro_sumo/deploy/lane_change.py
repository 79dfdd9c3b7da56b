"""SUMO's lane changer (LC2013) as a speed-commanding driver (``deploy.drivers``) models it
for ``deploy.merge = "handover"``: from how far ahead of where a vehicle must have left
its lane SUMO makes that change urgent (``strategic_reach_m``), and the look-ahead speed
that distance grows with (``lookahead_speeds``); for ``deploy.keep_right = "blocked"`` its
ban on overtaking on the right, for commanded cars beside a queue on their left
(``keep_right_caps``). Pure numpy.

LC2013: a change for the route is urgent once the distance left per change needed is below
v_la LOOK_FORWARD (x lcLookaheadLeft 2 to the left) + 2 (length + minGap), v_la the speed,
up at once, down with memory 0.9/s. A fixed 400 m before: on drawn 501 m0's lane 0 (three
changes, urgent 1,491 m ahead at 24 m/s) was commanded where SUMO's drivers slowed.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.states import VehicleStates

LC_LOOK_FORWARD_S = 10.0
LC_LOOKAHEAD_LEFT = 2.0
LC_LOOKAHEAD_MEMORY = 0.9  # per second
# MSVehicle::congested(): below 60 km/h a vehicle may pass slower traffic on its left.
CONGESTED_MPS = 60.0 / 3.6
# The headway of the Krauss follow speed LC2013's advice brakes to (SUMO's default tau) [s].
KRAUSS_TAU_S = 1.0
# A leader on the lane to the left is free (the ban does not bind) where the next vehicle
# ahead of it is at least this far, front to front (``blocked``).
FREE_HEADWAY_S = 2.0
FREE_SPACING_M = 10.0


def strategic_reach_m(
    offset: np.ndarray, lookahead_mps: np.ndarray, with_gap_m: np.ndarray
) -> np.ndarray:
    """How far before where it must have left its lane SUMO's lane changer (LC2013) makes a
    vehicle's change for its route urgent: ``offset`` lane changes (SUMO's best-lane
    offset, > 0 to the left) of laDist each, from its look-ahead speed and its length plus
    minGap ``with_gap_m``; 0 where it needs none."""
    side = np.where(offset > 0, LC_LOOKAHEAD_LEFT, 1.0)
    return np.abs(offset) * (lookahead_mps * LC_LOOK_FORWARD_S * side + 2.0 * with_gap_m)


def lookahead_speeds(lookahead_mps: np.ndarray, speed_mps: np.ndarray, dt_s: float) -> np.ndarray:
    """Each vehicle's look-ahead speed after a step at ``speed_mps``: the speed where it is
    higher or where there is none yet (NaN), else the last one decayed towards it with
    memory ``LC_LOOKAHEAD_MEMORY``. Where(la >= v, ...): a NaN compares False, so one
    comparison stands for isnan(la) | (v > la) (the same values, two array calls fewer)."""
    keep = 1.0 - (1.0 - LC_LOOKAHEAD_MEMORY) * dt_s
    la = lookahead_mps
    return np.where(la >= speed_mps, keep * la + (1.0 - keep) * speed_mps, speed_mps)


def no_pass_right_cap(
    speed: np.ndarray, left_speed: np.ndarray, left_gap: np.ndarray, decel: np.ndarray, dt: float
) -> np.ndarray:
    """LC2013's speed advice against overtaking on the right (``MSLCM_LC2013::_wantsChange``,
    VARIANT_20, SUMO's default lcOvertakeRight 0), which a speed command overrides: the most
    a vehicle at ``speed`` [m/s] may drive next step behind its nearest leader on the lane
    to its left (speed ``left_speed``, ``left_gap`` from its front less its minGap to that
    leader's back, negative alongside): the Krauss follow speed behind it (``decel``, tau
    ``KRAUSS_TAU_S``) or that leader's speed, whichever is higher, and at least one step's
    full braking; inf where the vehicle is congested (below ``CONGESTED_MPS``: SUMO lifts
    the ban) or that leader is not slower."""
    tau_b = decel * KRAUSS_TAU_S
    gap = np.maximum(left_gap, 0.0)
    follow = np.sqrt(tau_b * tau_b + left_speed * left_speed + 2.0 * decel * gap) - tau_b
    cap = np.maximum(np.maximum(left_speed, follow), speed - decel * dt)
    return np.where((speed >= CONGESTED_MPS) & (left_speed < speed), cap, np.inf)


def left_lane(lane: str, lanes: Mapping[str, object]) -> str | None:
    """The lane to the left of ``lane`` on its edge (SUMO's ``<edge>_<index>``) where it is
    in ``lanes``; None on a junction's internal lane or the leftmost lane."""
    if lane.startswith(":"):
        return None
    edge, _, index = lane.rpartition("_")
    left = f"{edge}_{int(index) + 1}"
    return left if left in lanes else None


def keep_right_caps(
    sc: SectionScenario,
    section: Section,
    shape_of: Mapping[str, tuple[float, float, float]],
    st: VehicleStates,
    rows: np.ndarray,
    cap: np.ndarray | None,
) -> np.ndarray | None:
    """With ``deploy.keep_right = "blocked"`` (and ``deploy.merge = "sumo"``): ``cap`` (per
    commanded vehicle, rows ``rows`` of the road's state ``st``; None: none) lowered to
    ``no_pass_right_cap`` where the vehicle's nearest leader on the lane to its left, on
    the same edge of ``section``, is slower and itself blocked (``blocked``): a commanded
    car passes a queue on its left no faster than SUMO's drivers do. Drawn 501's m0 lane 2
    beside the queue on lane 3: 16.6 m/s in the truth, 22-24 commanded. Not beside a free
    leader: the merge's commanded followers held behind free cars on the lane to their
    left closed the gaps a SUMO ramp car merges into (stood 23 steps at the acceleration
    lane's end). Not with
    ``policy.driver_speed = "drawn"``: SUMO's lane changer sorts the cars by their own
    speedFactor, to which a drawn factor is blind, and the ban passed the policy's slow
    left lane on Bremen (-3 m/s) to the lanes on its right (1.146 -> 1.292 m/s). Off by
    default: on drawn 549 the caps at its busy 3-lane entry (1,560 veh/h a lane, so every
    left leader at 2 s spacing counts as blocked) helped the lane drop's queue spill back to
    the entry (all 4 runs 4.39 -> 4.95 m/s); a blocked test at 1 s x v + 10 m instead gave
    549 4.23 but 501 3.00 (3.02 without the ban, 2.75 with it): 501's gain gone.
    ``shape_of``: vehicle -> (length, minGap, decel)."""
    d = sc.deploy
    if d.keep_right != "blocked" or d.merge != "sumo" or sc.policy.driver_speed == "drawn":
        return cap
    speed, pos, lanes = st.speed_mps, st.pos_m, st.lanes
    own = speed[rows]
    idx, target = [], []
    for i in np.flatnonzero(own >= CONGESTED_MPS).tolist():
        left = left_lane(lanes[rows[i]], section.lanes)
        if left is not None:
            idx.append(i)
            target.append(left)
    if not idx:
        return cap
    on: dict[str, list[int]] = {lane: [] for lane in target}
    for j, lane in enumerate(lanes):
        if lane in on:
            on[lane].append(j)
    order = {}
    for lane, got in on.items():
        js = np.array(got, dtype=np.int64)
        order[lane] = js[np.argsort(pos[js], kind="stable")]
    ids = st.ids
    left_speed, left_gap = np.full(len(idx), np.nan), np.full(len(idx), np.nan)
    for k, (i, lane) in enumerate(zip(idx, target, strict=True)):
        js, me = order[lane], rows[i]
        at = int(np.searchsorted(pos[js], pos[me], side="right"))
        if at < js.size and blocked(pos[js], speed[js], at):  # the nearest ahead on the left
            j = int(js[at])
            left_speed[k] = speed[j]
            left_gap[k] = pos[j] - shape_of[ids[j]][0] - pos[me] - shape_of[ids[me]][1]
    sel = np.array(idx)
    binds = left_speed < own[sel]  # NaN (none, or free): False
    if not np.count_nonzero(binds):
        return cap
    hit = sel[binds]
    decel = np.array([shape_of[ids[rows[i]]][2] for i in hit.tolist()])
    ro = np.full(len(rows), np.inf)
    ro[hit] = no_pass_right_cap(
        own[hit], left_speed[binds], left_gap[binds], decel, sc.simulation.step_length_s
    )
    return ro if cap is None else np.minimum(cap, ro)


def blocked(pos: np.ndarray, speed: np.ndarray, at: int) -> bool:
    """Whether the vehicle at index ``at`` of a lane's vehicles (``pos`` ascending, their
    ``speed``) is itself blocked: the next one ahead nearer than ``FREE_HEADWAY_S`` x v +
    ``FREE_SPACING_M`` front to front (``env.driver_speed``'s free test before it read the
    bumper gap, stop 38; measured with this one), or none ahead on the edge (it may be
    queued on the next)."""
    ahead = at + 1
    return ahead >= pos.size or pos[ahead] - pos[at] < FREE_HEADWAY_S * speed[at] + FREE_SPACING_M

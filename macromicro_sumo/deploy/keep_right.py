"""SUMO's lane changer (LC2013)'s ban on overtaking on the right, for commanded cars beside
a queue on their left (``deploy.keep_right = "blocked"``, ``keep_right_caps``): a speed
command overrides LC2013's speed advice, so a commanded car is capped to it. Pure numpy.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.states import VehicleStates

# MSVehicle::congested(): below 60 km/h a vehicle may pass slower traffic on its left.
CONGESTED_MPS = 60.0 / 3.6
# The headway of the Krauss follow speed LC2013's advice brakes to (SUMO's default tau) [s].
KRAUSS_TAU_S = 1.0
# A leader on the lane to the left is blocked (the ban binds behind it) where the next
# vehicle ahead of it is nearer than BLOCKED_HEADWAY_S x its speed + BLOCKED_SPACING_M, front
# to front (``blocked``): it follows that one at about a Krauss driver's headway (SUMO's
# default tau, ``KRAUSS_TAU_S``), held by it. At 2 s (stop 38) a dense free-flowing lane
# counted as blocked: drawn 549's entry, 1,560 veh/h a lane at 28 m/s, 65 m apart < 66 m.
BLOCKED_HEADWAY_S = KRAUSS_TAU_S
BLOCKED_SPACING_M = 10.0


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
    left leader at 2 s spacing counted as blocked) helped the lane drop's queue spill back to
    the entry (all 4 runs 4.38 -> 4.98 m/s). With ``blocked``'s 1 s (stop 39) a free-flowing
    left lane caps nobody: 549 4.16, 501 3.00 (3.02 off, 2.75 with the 2 s test: 501's gain
    is gone), both within the spread of headways 0.9-1.2 s (549 4.16-4.93, 501 2.98-3.24);
    no blocked test tried (speed below 0.7-0.8 x the limit or 2-4 m/s below the leader's
    own allowed speed, none ahead free, none in the first 150-300 m) kept 501's gain without
    549's loss. ``shape_of``: vehicle -> (length, minGap, decel)."""
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
    ``speed``) is itself blocked: the next one ahead nearer than ``BLOCKED_HEADWAY_S`` x v +
    ``BLOCKED_SPACING_M`` front to front (it follows at about a Krauss driver's 1 s), or none
    ahead on the edge (it may be queued on the next)."""
    ahead = at + 1
    reach = BLOCKED_HEADWAY_S * speed[at] + BLOCKED_SPACING_M
    return ahead >= pos.size or pos[ahead] - pos[at] < reach

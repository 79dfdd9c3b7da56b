"""SUMO's lane changer (LC2013) as a speed-commanding driver (``deploy.drivers``) models it
for ``deploy.merge = "handover"``: from how far ahead of where a vehicle must have left
its lane SUMO makes that change urgent (``strategic_reach_m``), and the look-ahead speed
that distance grows with (``lookahead_speeds``), and the distance it reads against that
reach in a queue (``usable_distance_m``, over ``continuation_lanes``). Its ban on
overtaking on the right for ``deploy.keep_right`` is in ``deploy.keep_right``. Pure numpy.

LC2013: a change for the route is urgent once the distance left per change needed is below
v_la LOOK_FORWARD (x lcLookaheadLeft 2 to the left) + 2 (length + minGap), v_la the speed,
up at once, down with memory 0.9/s. A fixed 400 m before: on drawn 501 m0's lane 0 (three
changes, urgent 1,491 m ahead at 24 m/s) was commanded where SUMO's drivers slowed.
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.road.physics import constants
from macromicro_sumo.road.section import Section

LC_LOOK_FORWARD_S = 10.0
LC_LOOKAHEAD_LEFT = 2.0
LC_LOOKAHEAD_MEMORY = 0.9  # per second
# MSLCM_LC2013::_wantsChange reads the distance left less the best lane's occupation:
# usableDist = currentDist - posOnLane - best.occupation * JAM_FACTOR, JAM_FACTOR 1 (its
# 2, "VARIANT_8", is commented out in SUMO's source). best.occupation (MSLaneChanger) is the
# length + minGap of the vehicles ahead on the best lane of the edge plus those on every
# lane of its continuation (MSVehicle::LaneQ::nextOccupation, getBruttoVehLenSum).
JAM_FACTOR = 1.0


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
    # The two weights as 0-d arrays kept per dt (``road.physics.constants``): the same
    # products for float64 operands (every caller's), without numpy's conversion of a
    # Python float each call (every step).
    old, new = constants(keep, 1.0 - keep)
    la = lookahead_mps
    return np.where(la >= speed_mps, old * la + new * speed_mps, speed_mps)


def usable_distance_m(ahead_m: np.ndarray, occupation_m: np.ndarray) -> np.ndarray:
    """LC2013's usable distance: the distance ``ahead_m`` to where a vehicle must have left
    its lane less its best lane's occupation ``occupation_m`` (``JAM_FACTOR``): in a queue
    on the lane it must reach the change is urgent far before the plain reach."""
    return ahead_m - JAM_FACTOR * occupation_m


def continuation_lanes(section: Section) -> dict[str, tuple[str, ...]]:
    """Per lane of ``section``'s edges, the lanes that SUMO's best lanes continue it on
    (bestContinuations after the lane itself) within the section: on each next edge the
    lane it links to (``Section.links``) that carries on (not a ``route_ends`` lane), the
    nearest in index (the lower of two); none past a lane that ends or links nowhere, or
    past the section's last edge (a loop: once round, up to the lane's own edge)."""
    ends, links, n = section.route_ends, section.links, len(section.edge_ids)
    out: dict[str, tuple[str, ...]] = {}
    for e, edge in enumerate(section.edge_ids):
        for j in range(int(section.n_lanes[e])):
            chain, k, i = [], e, j
            for _ in range(n - 1):
                if not section.closed and k == n - 1:
                    break
                linked = np.flatnonzero(links[k, i])
                if not linked.size or ends[k, i]:
                    break
                nxt = (k + 1) % n
                on = [int(x) for x in linked if not ends[nxt, x]] or linked.tolist()
                i = min(on, key=lambda x: (abs(x - i), x))
                k = nxt
                chain.append(f"{section.edge_ids[k]}_{i}")
            out[f"{edge}_{j}"] = tuple(chain)
    return out

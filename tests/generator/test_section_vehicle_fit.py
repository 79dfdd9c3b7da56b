"""Stage I puts hidden vehicles only where a vehicle fits: not inside a long observed
leader (a truck), not on a lane index that a junction does not have.

Both were Stage II evaluation collisions on freshly drawn networks (issue 17): psi's
smallest spacing is the shortest vType's length plus the minimum gap, and the generator
kept it behind every leader, so a car went into a 12 m truck's rear; a junction was given
the upstream edge's lane count, and a vehicle on a junction lane that does not exist was
put by SUMO onto the next edge's start, into whoever stood there.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from section_checks import lane_is_there
from test_section_generator import S_MIN, synthetic, untrained

from macromicro_sumo.generator.section_sampler import complete_section, uniform_completion
from macromicro_sumo.generator.section_scene import Road, scene_gaps
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.section import Section

CAR_M, TRUCK_M = 5.0, 12.0  # S_MIN = the car's length + a 2.5 m minimum gap
BRAKE_MPS2, REACTION_S = 4.5, 1.0


def test_a_truck_keeps_its_length_free_behind_it(bremen: Section) -> None:
    """A car at 50 m, a truck at 100 m (fronts): a new vehicle between them must stay
    S_MIN + 7 m behind the truck's front, S_MIN behind a car's."""
    road = Road.of(bremen)
    lane = torch.zeros(1, 2, dtype=torch.long)
    arc = torch.tensor([[50.0, 100.0]], dtype=torch.float64)
    present = torch.ones(1, 2, dtype=torch.bool)
    speed = torch.full((1, 2), 20.0)
    for lead_m in (CAR_M, TRUCK_M):
        extra = torch.tensor([[0.0, lead_m - CAR_M]], dtype=torch.float64)
        g = scene_gaps(lane, arc, speed, present, road, torch.tensor([S_MIN]), None, extra)
        j = int(torch.nonzero((g.start[0] == 50.0) & (g.lane[0] == 0))[0, 0])
        assert float(g.start[0, j] + g.hi[0, j]) == pytest.approx(100.0 - S_MIN - (lead_m - CAR_M))


def test_no_vehicle_is_generated_inside_a_truck(bremen: Section) -> None:
    """Dense scenes on Bremen in which every observed vehicle is a truck: every generated
    vehicle's front is at least the minimum gap behind its leader's rear, and can stop
    behind it with one step of reaction (SUMO's safe speed)."""
    snaps = synthetic(bremen, 4, seed=4, mean_gap_m=40.0, p_obs=0.5)
    obs = snaps.valid & snaps.observed
    snaps = dataclasses.replace(snaps, length_m=np.where(obs, TRUCK_M, CAR_M))
    comp = complete_section(untrained(), bremen, snaps, snaps.k_true, 20, 0, BRAKE_MPS2, REACTION_S)
    n = snaps.arc_m.shape[1]
    min_gap = S_MIN - CAR_M
    behind_trucks = 0
    for i in range(len(snaps)):
        on = np.flatnonzero(comp.valid[i])
        length = np.where(on < n, TRUCK_M, CAR_M)  # observed slots first, then generated
        lane, arc, v = comp.lane[i, on], comp.arc_m[i, on], comp.speed_mps[i, on]
        gen = comp.generated[i, on]
        for ln in np.unique(lane):  # per lane index: the generator's gaps
            k = np.flatnonzero(lane == ln)
            k = k[np.argsort(arc[k])]
            bumper = arc[k[1:]] - length[k[1:]] - arc[k[:-1]]
            touched = gen[k[1:]] | gen[k[:-1]]
            assert np.all(bumper[touched] >= min_gap - 1e-6), (i, ln, bumper[touched].min())
        leader, spacing = section_leaders(bremen, lane, arc)  # the environment's leaders
        for f in np.flatnonzero(gen & (leader >= 0)):
            j = leader[f]
            if gen[j]:
                continue
            behind_trucks += 1
            room = 2.0 * BRAKE_MPS2 * max(0.0, spacing[f] - S_MIN - (TRUCK_M - CAR_M))
            bt = BRAKE_MPS2 * REACTION_S
            assert v[f] <= math.sqrt(bt * bt + v[j] ** 2 + room) - bt + 1e-6, (i, f)
    assert behind_trucks > 20, behind_trucks  # the check saw enough cars behind trucks


def test_junction_lanes_are_the_lanes_they_lead_to(bremen: Section) -> None:
    """Bremen's E0 gains a lane on the right (SUMO's lane 0 there, the generator's lane 3:
    lanes are numbered along the connections): the junction onto E0 has the generator's
    lanes 0-2 (they lead onto E0's SUMO lanes 1-3), not the ramp's lane 3, which nothing on
    the section leads into; the junction after it lanes 0-2 too (E0's lanes 1-3 continue
    onto the next edge's 0-2)."""
    road = Road.of(bremen)
    e0 = bremen.edge_ids.index("E0")
    onto = float(bremen.offsets_m[e0] - 0.5 * bremen.junction_m[e0 - 1])
    after = float(bremen.offsets_m[e0] + bremen.lengths_m[e0] + 0.5 * bremen.junction_m[e0])
    expect = {onto: [True, True, True, False], after: [True, True, True, False]}
    for arc, lanes in expect.items():
        got = road.has_lane(torch.arange(4), torch.full((4,), arc, dtype=torch.float64))
        assert got.tolist() == lanes, arc
        sumo = road.sumo_lanes(np.arange(3), np.full(3, arc))
        assert all(lane_is_there(bremen, int(ln), arc) for ln in sumo)
    assert road.sumo_lanes(np.arange(3), np.full(3, onto)).tolist() == [1, 2, 3]
    # ... and a gap on the ramp's lane across the junction onto E0 offers no point inside it
    a, b = onto - 0.4 * bremen.junction_m[e0 - 1], onto + 0.4 * bremen.junction_m[e0 - 1]
    assert road.nearest_on_lane(3, a, b, onto) is None


def test_a_projected_vehicle_goes_onto_the_lane_of_its_gap(bremen: Section) -> None:
    """Dense scenes where trials fail and vehicles are projected: a projection into a gap
    of another lane than the failed trial's puts the vehicle on that gap's lane (it kept
    the trial's lane: vehicles at another's exact position, and on lanes that do not
    exist there)."""
    snaps = synthetic(bremen, 2, seed=4, mean_gap_m=25.0, p_obs=0.5)
    comp = complete_section(untrained(), bremen, snaps, snaps.k_true, 20, 0, BRAKE_MPS2, REACTION_S)
    assert comp.projections.sum() > 10
    for i in range(len(snaps)):
        on = np.flatnonzero(comp.valid[i])
        lane, arc, gen = comp.lane[i, on], comp.arc_m[i, on], comp.generated[i, on]
        for ln in np.unique(lane):
            k = np.flatnonzero(lane == ln)
            k = k[np.argsort(arc[k])]
            touched = gen[k[1:]] | gen[k[:-1]]
            assert np.all(np.diff(arc[k])[touched] >= S_MIN - 1e-6), (i, ln)
        for ln, x in zip(lane[gen], arc[gen], strict=True):
            assert lane_is_there(bremen, int(ln), float(x)), (i, ln, x)


def test_the_uniform_baseline_draws_lanes_that_exist_there(bremen: Section) -> None:
    """The baseline's lane is drawn among those that exist at its position: in the 13 m
    of Bremen's junctions, not among the upstream edge's lanes."""
    snaps = synthetic(bremen, 8, seed=2)
    k = np.full(len(snaps), 400)
    comp = uniform_completion(None, bremen, snaps, k, 1, 0)
    gen = comp.generated
    ends = bremen.offsets_m + bremen.lengths_m
    e = bremen.edge_index(comp.arc_m[gen])
    assert (comp.arc_m[gen] > ends[e]).sum() > 10  # some fall into a junction
    for ln, x in zip(comp.lane[gen], comp.arc_m[gen], strict=True):
        assert lane_is_there(bremen, int(ln), float(x)), (ln, x)
    assert set(np.unique(comp.lane[gen])) == {0, 1, 2, 3}

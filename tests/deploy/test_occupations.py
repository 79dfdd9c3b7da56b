"""``MergeYield.occupations_m``, LC2013's best-lane occupation that ``deploy.merge_reach =
"occupation"`` subtracts from the distance left (``usable_m``): per vehicle that must
leave its lane, the length + minGap of the vehicles ahead of it on the lane it must reach
plus those on every lane that lane continues on; 0 for a vehicle that need not change and
on a junction's internal lane. Several vehicles share one best lane here (the values are
read once per lane for all of them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from deploy_nets import lane_drop_net

from macromicro_sumo.deploy.merge_yield import MergeYield
from macromicro_sumo.deploy.slots import VehicleSlots
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.states import VehicleStates

# vehicle -> (lane, position [m], length, minGap, best-lane offset)
VEHICLES = {
    "e1": ("A_0", 300.0, 5.0, 2.5, 1),  # must reach A_1: t1 ahead of it
    "e2": ("A_0", 100.0, 4.5, 2.0, 1),  # must reach A_1: t1 and t2 ahead of it
    "j1": (":n1_0_0", 2.0, 5.0, 2.5, 1),  # on the junction: not read
    "t1": ("A_1", 400.0, 5.0, 2.5, 0),
    "t2": ("A_1", 200.0, 12.0, 2.5, 0),
    "t3": ("A_1", 50.0, 5.0, 2.5, 0),  # behind both: not counted
    "b1": ("B_0", 100.0, 5.0, 2.5, 0),  # B_0 continues A_1: all of it counted
    "b2": ("B_0", 50.0, 4.5, 2.0, 0),
}


class Host(MergeYield):
    """The state ``occupations_m`` reads of ``SectionSpeedDriver``."""

    def __init__(self, section, shape_of: dict[str, tuple[float, float, float]]) -> None:
        self.section, self.shape_of, self.slots = section, shape_of, VehicleSlots()


def test_occupations_sum_the_best_lane_ahead_and_its_continuation(tmp_path: Path) -> None:
    net = lane_drop_net(tmp_path)
    host = Host(
        read_section(net, ["A", "B"], False),
        {v: (length, gap, 4.5) for v, (_, _, length, gap, _) in VEHICLES.items()},
    )
    ids = tuple(sorted(VEHICLES))
    st = VehicleStates(
        ids,
        [VEHICLES[v][0] for v in ids],
        np.array([VEHICLES[v][1] for v in ids]),
        np.zeros(len(ids)),
        np.zeros(len(ids)),
    )
    driven = ["e1", "e2", "j1", "t1", "t3"]
    for v in driven:
        host.slots.add(v)
    slots = host.slots.slots(driven)
    host.slots.lane_end.offset[slots] = [VEHICLES[v][4] for v in driven]
    rows = np.array([st.index[v] for v in driven])
    occ = host.occupations_m(rows, [VEHICLES[v][0] for v in driven], slots, st)
    on_b = 7.5 + 6.5
    np.testing.assert_array_equal(occ, [7.5 + on_b, 7.5 + 14.5 + on_b, 0.0, 0.0, 0.0])
    # Nobody must change: zeros, SUMO's lane table not read.
    host.slots.lane_end.offset[slots] = 0
    assert not host.occupations_m(rows, [VEHICLES[v][0] for v in driven], slots, st).any()

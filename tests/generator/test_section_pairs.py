"""Stage I's pair check along the network's lanes (``drop_unsafe_pairs``).

On game/cross lane 1 of 1si (three lanes) continues through the junction onto 2o's only
lane, lane 0: the generator's gaps, one per lane index, do not see a car on lane 1 at the
stop line and one at lane index 0 just past it as neighbours (drawn net 501: cars 0.6 m
apart, or a slow car 6.5 m ahead of an observed one at 21 m/s: collisions in the first
step of Stage II's evaluation).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import sumo

from macromicro_sumo.generator.section_pairs import drop_unsafe_pairs
from macromicro_sumo.generator.section_sampler import SectionCompletion
from macromicro_sumo.road.section import read_section

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


def completion(lane, arc, speed, generated) -> SectionCompletion:
    n = len(arc)
    return SectionCompletion(
        lane=np.array([lane], dtype=np.int64),
        arc_m=np.array([arc], dtype=float),
        speed_mps=np.array([speed], dtype=float),
        valid=np.ones((1, n), dtype=bool),
        generated=np.array([generated], dtype=bool),
        trials=np.zeros(1),
        projections=np.zeros(1),
    )


def test_pairs_across_a_lane_index_change_are_checked() -> None:
    sec = read_section(CROSS, ["1fi", "1si", "2o", "2fo"], False)
    end = float(sec.offsets_m[1] + sec.lengths_m[1])
    args = (sec, np.array([6.5]), 4.5, 0.5, np.zeros((1, 4)), None)
    # 0: observed on 2o; 1, 2: generated 0.6 m apart across the junction (lane 1 -> 0).
    comp = completion([0, 1, 0, 0], [end - 40.0, end - 0.3, end + 0.3, end + 60.0],
                      [10.0, 5.0, 5.0, 10.0], [False, True, True, False])  # fmt: skip
    assert drop_unsafe_pairs(comp, *args).tolist() == [1]
    np.testing.assert_array_equal(comp.valid[0], [True, False, True, True])  # the follower
    # An observed car at 21 m/s 6.5 m behind a generated one at 4.5 m/s, which must stop
    # behind a car standing in the junction: the observed car cannot; the generated one goes.
    comp = completion([1, 1, 0, 0], [end - 20.0, end - 13.5, end + 3.0, end + 60.0],
                      [21.0, 4.5, 0.0, 10.0], [False, True, False, False])  # fmt: skip
    assert drop_unsafe_pairs(comp, *args).tolist() == [1]
    np.testing.assert_array_equal(comp.valid[0], [True, False, True, True])
    # Far enough apart at matching speeds: kept.
    comp = completion([1, 1, 0], [end - 100.0, end - 40.0, end + 30.0],
                      [10.0, 10.0, 10.0], [False, True, True])  # fmt: skip
    assert drop_unsafe_pairs(comp, *args).tolist() == [0]
    assert comp.valid.all()

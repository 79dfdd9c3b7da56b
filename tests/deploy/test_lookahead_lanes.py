"""The deployment's look-ahead features are the envs' (``Section.lookahead``): the next
edge's limit is read on the lane a vehicle continues onto, which an on-ramp added on the
right shifts by one index at the boundary."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import netconvert

from macromicro_sumo.deploy.observe import LaneTable
from macromicro_sumo.road.section import read_section

# b's lanes, right to left: the ramp's lane, then the two through lanes, each its own limit.
B_LIMITS = (20.0, 25.0, 30.0)


def merge_with_lane_limits(folder: Path) -> Path:
    """a (2 lanes) -> b (3 lanes, the ramp r joins on the right) -> c (2 lanes); a_0 -> b_1,
    a_1 -> b_2, r_0 -> b_0; b's lanes have the limits ``B_LIMITS``."""
    lanes = "".join(f'<lane index="{i}" speed="{v}"/>' for i, v in enumerate(B_LIMITS))
    return netconvert(
        folder,
        '<node id="n0" x="0" y="0"/><node id="n1" x="300" y="0"/>'
        '<node id="n2" x="600" y="0"/><node id="n3" x="900" y="0"/>'
        '<node id="r0" x="0" y="-60"/>',
        '<edge id="a" from="n0" to="n1" numLanes="2" speed="30"/>'
        '<edge id="r" from="r0" to="n1" numLanes="1" speed="25"/>'
        f'<edge id="b" from="n1" to="n2" numLanes="3" speed="30">{lanes}</edge>'
        '<edge id="c" from="n2" to="n3" numLanes="2" speed="30"/>',
        '<connection from="a" to="b" fromLane="0" toLane="1"/>'
        '<connection from="a" to="b" fromLane="1" toLane="2"/>'
        '<connection from="r" to="b" fromLane="0" toLane="0"/>'
        '<connection from="b" to="c" fromLane="1" toLane="0"/>'
        '<connection from="b" to="c" fromLane="2" toLane="1"/>',
        name="merge_limits",
    )


def test_lookahead_reads_the_limit_of_the_lane_continued_onto(tmp_path: Path) -> None:
    sec = read_section(merge_with_lane_limits(tmp_path), ["a", "b", "c"], closed=False)
    np.testing.assert_allclose(sec.limits_mps[1, :3], B_LIMITS)
    table = LaneTable(sec)
    rows = {lane: table.code[lane] for lane in ("a_0", "a_1")}
    # a_0 continues onto b_1 (25 m/s), a_1 onto b_2 (30): the index-wise lanes b_0 / b_1
    # would read 20 / 25.
    assert table.next_limit_mps[rows["a_0"]] == B_LIMITS[1]
    assert table.next_limit_mps[rows["a_1"]] == B_LIMITS[2]
    # The distance to b's start, for a vehicle 100 m into a, agrees with the envs' definition.
    a0 = table.code["a_0"]
    arc = table.arc0_m[a0] + 100.0 * table.arc_per_m[a0]
    limit, ahead = sec.lookahead(np.array([0]), np.array([arc]), np.array([0]), np.array([30.0]))
    assert limit[0] == B_LIMITS[1]
    np.testing.assert_allclose(table.next_start_m[a0] - arc, ahead[0])
    assert 150.0 < ahead[0] < 201.0  # a is 300 m long, less the junction's cut

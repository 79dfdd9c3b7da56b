"""The deployment's look-ahead features are the envs' (``Section.lookahead``): the next
edge's limit is read on the lane a vehicle continues onto, which an on-ramp added on the
right shifts by one index at the boundary."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "road"))

from test_section_leaders import EDGES, build_merge_net  # noqa: E402

from macromicro_sumo.deploy.observe import LaneTable  # noqa: E402
from macromicro_sumo.road.section import read_section  # noqa: E402

# b's lanes, right to left: the ramp's lane, then the two through lanes, each its own limit.
B_LIMITS = (20.0, 25.0, 30.0)


def test_lookahead_reads_the_limit_of_the_lane_continued_onto(tmp_path: Path) -> None:
    sec = read_section(build_merge_net(tmp_path, B_LIMITS), EDGES, closed=False)
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

"""``deploy.merge_follow = "last_lane"``: a commanded blocker held after a merge yield on
the leftmost lane of its edge (``merge_yield.last_lanes``: no lane to move over to) keeps
following SUMO's own slower speed while SUMO wants it slower (``yield_caps``' follow). At
fresh motorway 1803's 4 -> 1 drop LC2013 asked such a follower to fall back by less than
the yield's tolerance a step; asked, held a step, released and re-accelerated, it stayed
level with an urgent merger to the lane end, where the merger stood (hF49's trace)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from deploy_nets import lane_drop_net, merge_net

from macromicro_sumo.deploy.merge_yield import last_lanes, yield_caps
from macromicro_sumo.road.section import read_section


def test_yield_caps_follow_keeps_a_held_blocker_on_sumos_speed() -> None:
    """Held, not asked (SUMO's own speed less than the tolerance below): where follow is on
    and own is below v, own (at least v - decel dt), counted as asked (held again next
    step); held at v where own is not below v or follow is off; not held: inf; an asked
    one as without follow."""
    v = np.full(6, 25.0)
    safe = np.full(6, 30.0)
    own = np.array([24.6, 24.6, 25.2, 23.0, 24.6, 20.0])
    held = np.array([True, True, True, True, False, True])
    follow = np.array([True, False, True, True, True, True])
    decel = np.full(6, 4.5)
    cap, asked = yield_caps(own, v, safe, decel, 0.5, held, follow)
    np.testing.assert_allclose(cap, [24.6, 25.0, 25.0, 23.0, np.inf, 25.0 - 2.25])
    assert asked.tolist() == [True, False, False, True, False, True]
    base, base_asked = yield_caps(own, v, safe, decel, 0.5, held)
    np.testing.assert_allclose(base, [25.0, 25.0, 25.0, 23.0, np.inf, 22.75])
    assert base_asked.tolist() == [False, False, False, True, False, True]
    # Without held, follow changes nothing (it only extends a hold).
    free, free_asked = yield_caps(own, v, safe, decel, 0.5, None, follow)
    np.testing.assert_allclose(free, [np.inf, np.inf, np.inf, 23.0, np.inf, 22.75])
    assert free_asked.tolist() == [False, False, False, True, False, True]


def test_last_lanes_are_each_edges_leftmost(tmp_path: Path) -> None:
    """The lane drop (A 2 lanes -> B 1): A's lane 1 and B's lane 0; the merge net's main
    line (A 2, B 3 with an acceleration lane, C 2): A_1, B_2, C_1, never an internal lane
    nor a lane with one to its left (B_1, where the acceleration lane's followers are)."""
    (tmp_path / "d").mkdir()
    drop = read_section(lane_drop_net(tmp_path / "d"), ["A", "B"], False)
    assert last_lanes(drop) == frozenset({"A_1", "B_0"})
    net, _ = merge_net(tmp_path / "m")
    merge = read_section(net, ["A", "B", "C"], False)
    got = last_lanes(merge)
    assert got == frozenset({"A_1", "B_2", "C_1"}), got
    assert not any(lane.startswith(":") for lane in got)

"""``deploy.merge_follow = "last_lane"``: a blocker that may follow (on its edge's last
lane, at ``FOLLOW_MIN_MPS`` or more), on a lane moving at ``FOLLOW_FREE_FRACTION`` of its
limit or more (``free_lanes``), yields where SUMO's own speed is more than
``deploy.merge_follow_tolerance_mps`` (0.5 m/s) below its speed and safe speed, not only more than the
yield's ``MERGE_YIELD_TOLERANCE_MPS`` (1 m/s). Why: LC2013 asks the follower of an urgent
merger far behind it to fall back gently, 0.1-0.9 m/s a 0.5 s step; under 1 m/s the
commanded follower was never asked, closed on its merger for 10 s (70 -> 30 m at 29 -> 27
m/s: fresh motorway 1803, run 2) and the merger stood 100 s at the lane end, where SUMO's
own drivers leave the ending lanes early and none stands (stop 51, hD51)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from deploy_nets import lane_drop_net
from test_merge_follow import Follows, platoon_run

from macromicro_sumo.deploy.merge_yield import (
    FOLLOW_FREE_FRACTION,
    FOLLOW_MIN_MPS,
    MERGE_YIELD_TOLERANCE_MPS,
    free_lanes,
    yield_caps,
)
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.deploy_settings import DeployConfig


def test_yield_caps_asks_a_follower_at_its_tolerance() -> None:
    """Not held: SUMO's own speed 0.7 m/s below (between the two tolerances) asks a
    vehicle with the gentle ask on (capped at own, counted as asked), not one without; 0.3
    below asks neither; 1.5 below asks both."""
    v = np.full(6, 30.0)
    safe = np.full(6, 35.0)
    own = np.array([29.3, 29.3, 29.7, 29.7, 28.5, 28.5])
    gentle = np.array([True, False, True, False, True, False])
    held = np.zeros(6, bool)
    tolerance = DeployConfig().merge_follow_tolerance_mps
    assert MERGE_YIELD_TOLERANCE_MPS > 0.7 > tolerance > 0.3
    cap, asked = yield_caps(own, v, safe, np.full(6, 4.5), 0.5, held, gentle, gentle, tolerance)
    np.testing.assert_allclose(cap, [29.3, np.inf, np.inf, np.inf, 28.5, 28.5])
    assert asked.tolist() == [True, False, False, False, True, True]
    # At the yield's own tolerance (stop 50's rule) the gentle ask adds nothing.
    old = yield_caps(own, v, safe, np.full(6, 4.5), 0.5, held, gentle, gentle, 1.0)[1]
    assert old.tolist() == [False, False, False, False, True, True]


def test_free_lanes_by_the_lanes_mean_speed(tmp_path: Path) -> None:
    """The lane drop's last lanes (A_1, B_0; limits from the net): a lane whose vehicles'
    mean speed is at least ``FOLLOW_FREE_FRACTION`` of its limit is free, a slower one (a
    queue) is not; vehicles on other lanes do not count."""
    (tmp_path / "d").mkdir()
    section = read_section(lane_drop_net(tmp_path / "d"), ["A", "B"], False)
    e, i = section.lanes["A_1"][:2]
    limit = float(section.limits_mps[e, i])
    on = ["A_1", "A_1", "B_0", "B_0", "A_0"]
    fast = FOLLOW_FREE_FRACTION * limit + 0.5
    speed = np.array([fast, fast, 2.0, 4.0, 0.0])
    assert free_lanes(section, {"A_1", "B_0"}, on, speed) == frozenset({"A_1"})
    speed[1] = FOLLOW_FREE_FRACTION * limit - 2.0  # the mean now below the fraction
    assert free_lanes(section, {"A_1"}, on, speed) == frozenset()


class Asked(Follows):
    """Also records (step, vehicle) -> (in ``gentle``, safe speed) of each blocker."""

    extra: dict[tuple[int, str], tuple[bool, float]]

    def yields(self, sim, vids, near, speed, safe):  # type: ignore[no-untyped-def]
        for i in near:
            self.extra[(self.steps, vids[i])] = (vids[i] in self.gentle, float(safe[i]))
        return super().yields(sim, vids, near, speed, safe)


def test_a_follower_is_asked_below_the_yields_tolerance(tmp_path: Path) -> None:
    """The platoon of 14 cars at 33 m/s on the last lane and its 6 mergers (test_merge_follow),
    all commanded by an IDM-cloned policy, 40 s: every blocker that may follow on a free lane
    (A's lane 1, in ``gentle``) whose own speed is between 0.5 and 1 m/s below its speed and safe speed
    is capped there (at own, at least v - decel dt), not left to the policy (with the
    1 m/s tolerance alone: capped only when held from the step before); all 6 mergers get
    in; nobody collides."""
    sc, drv, sim = platoon_run(tmp_path, Asked)
    drv.extra = {}
    dt = sc.simulation.step_length_s
    on_b: set[str] = set()
    collisions = 0
    try:
        for _ in range(int(40.0 / dt)):
            drv.before_step(sim)
            sim.step()
            collisions += sim.collisions()
            st = sim.vehicle_states()
            on_b.update(v for v, lane in zip(st.ids, st.lanes, strict=True) if v[0] == "m" and lane == "B_0")  # fmt: skip
    finally:
        sim.close()
    gentle = []
    for s, v, lane, speed, own, cap in drv.rows:
        on_free, safe = drv.extra[(s, v)]
        ask = min(speed, safe) - own
        if on_free and lane == "A_1" and speed >= FOLLOW_MIN_MPS and 0.5 < ask <= 1.0:
            gentle.append((speed, own, cap))
    assert len(gentle) > 3, len(gentle)
    for speed, own, cap in gentle:
        assert cap <= max(own, speed - 4.5 * dt) + 1e-9, (speed, own, cap)
    assert on_b == {f"m{k}" for k in range(6)}
    assert collisions == 0

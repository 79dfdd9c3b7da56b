"""``deploy.merge_follow = "last_lane"``: a commanded blocker held after a merge yield on
the leftmost lane of its edge (``merge_yield.last_lanes``: no lane to move over to), at
``FOLLOW_MIN_MPS`` or more, keeps following SUMO's own slower speed while SUMO wants it slower (``yield_caps``' follow). At
fresh motorway 1803's 4 -> 1 drop LC2013 asked such a follower to fall back by less than
the yield's tolerance a step; asked, held a step, released and re-accelerated, it stayed
level with an urgent merger to the lane end, where the merger stood (hF49's trace)."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import numpy as np
from deploy_nets import lane_drop_net, lane_drop_traffic, merge_net, recorded_drive

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.merge_yield import FOLLOW_MIN_MPS, last_lanes, yield_caps
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.simulation import Simulation

F = TypeVar("F", bound="Follows")

# Cars without dawdling: SUMO's own speed below a command is its lane changer's ask
IDM = (
    '<vType id="car" carFollowModel="IDM" length="5" minGap="2.5" accel="2.6" decel="4.5" '
    'sigma="0" tau="1.0" speedFactor="1.0" speedDev="0"/>'
)


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


class Follows(SectionSpeedDriver):
    """Records each blocker's step, ID, lane, speed, SUMO's own speed and cap (inf: none)."""

    rows: list[tuple[int, str, str, float, float, float]]

    def yields(self, sim, vids, near, speed, safe):  # type: ignore[no-untyped-def]
        cap = super().yields(sim, vids, near, speed, safe)
        ids = [vids[i] for i in near]
        own = sim.own_speeds(ids)
        st = sim.vehicle_states()
        lanes = dict(zip(st.ids, st.lanes, strict=True))
        for k, i in enumerate(near):
            row = (self.steps, vids[i], lanes[vids[i]], float(speed[i]), float(own[k]))
            self.rows.append((*row, float(cap[i])))
        return cap


def _platoon_and_mergers(folder: Path) -> tuple[Path, Path]:
    """A fast lane drop (A 2 lanes, 600 m -> B 1 lane, 400 m, both 36 m/s; A's lane 0
    ends): a platoon of 14 IDM cars (no dawdling) on A's lane 1 at 33 m/s, 24 m apart, and
    6 on the ending lane 0 at 33 m/s, 30 m apart from 350 m, level with it: each must get
    into the platoon before 600 m, the blockers above ``FOLLOW_MIN_MPS``."""
    net = lane_drop_net(folder, speed_mps=36.0)
    platoon, mergers = [340 - 24 * k for k in range(14)], [350 - 30 * k for k in range(6)]
    return net, lane_drop_traffic(folder, IDM, platoon, mergers, 33.0)


def platoon_run(tmp_path: Path, driver: type[F]) -> tuple[SectionScenario, F, Simulation]:
    """The platoon and its mergers (40 s, ``merge_follow = "last_lane"``), every car
    commanded by ``driver`` with a policy cloned from IDM (36 m/s): ``recorded_drive``."""
    net, routes = _platoon_and_mergers(tmp_path)
    return recorded_drive(tmp_path, net, routes, driver, 40.0, 36.0, merge_follow="last_lane")


def test_held_blockers_on_the_last_lane_follow_and_mergers_get_in(tmp_path: Path) -> None:
    """The platoon and its mergers, every car commanded by a policy cloned from IDM (36 m/s),
    occupation with ``merge_follow = "last_lane"``, 40 s: every blocker on A's lane 1 (the
    last lane) at ``FOLLOW_MIN_MPS`` or more that was asked or followed the step before and
    that SUMO wants slower now is capped at SUMO's own speed (at least v - decel dt), never
    held at or released above its speed (with "off": held at 18.01 where SUMO wanted 17.33,
    in the first version of this scene); no merger is left standing at the lane end: all 6
    get in (one waits 8.5 s, 17 steps, below 1 m/s); nobody collides."""
    sc, drv, sim = platoon_run(tmp_path, Follows)
    assert sc.deploy.merge_reach == "occupation"
    dt = sc.simulation.step_length_s
    standing = 0
    on_b: set[str] = set()
    try:
        for _ in range(int(40.0 / dt)):
            drv.before_step(sim)
            sim.step()
            st = sim.vehicle_states()
            for v, lane, speed in zip(st.ids, st.lanes, st.speed_mps.tolist(), strict=True):
                if v.startswith("m") and lane == "A_0" and speed < 1.0:
                    standing += 1
                if v.startswith("m") and lane.startswith("B"):
                    on_b.add(v)
        collisions = sim.collisions()
    finally:
        sim.close()
    rows = {(s, v): (lane, speed, own, cap) for s, v, lane, speed, own, cap in drv.rows}
    capped = {(s, v) for (s, v), (_, speed, _, cap) in rows.items() if cap < speed}
    again = [
        rows[(s + 1, v)]
        for s, v in capped
        if (s + 1, v) in rows and rows[(s + 1, v)][0] == "A_1"
        and rows[(s + 1, v)][1] >= FOLLOW_MIN_MPS and rows[(s + 1, v)][2] < rows[(s + 1, v)][1]
    ]  # fmt: skip
    assert len(again) > 3, (len(capped), len(again))
    for _lane, speed, own, cap in again:
        assert cap <= max(own, speed - 4.5 * dt) + 1e-9, (speed, own, cap)
    assert standing < 40, standing  # 17 steps (8.5 s) for one merger before it gets in
    assert on_b == {f"m{k}" for k in range(6)}
    assert collisions == 0

"""A lane drop with a queue on the through lane (drawn 522's m0, 2 lanes dropping to 1):
LC2013 makes the change out of the ending lane urgent at its usable distance, the distance
left less the best lane's occupation (``deploy.lane_change.usable_distance_m``), so in a
queue from far before the plain reach (``strategic_reach_m``). With the occupation the
hand-over starts there too, and with ``yield_all`` the commanded car on the through lane
that blocks the change takes SUMO's cooperative slow-down, as for any vehicle that must
leave its lane."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import small_section_scenario
from deploy_nets import CAR, idm_agent, lane_drop_net

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.lane_change import (
    JAM_FACTOR,
    continuation_lanes,
    strategic_reach_m,
    usable_distance_m,
)
from macromicro_sumo.deploy.merge_yield import drop_chain_lanes
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

SLOW = ["s0"]  # SUMO's own slow car at the head of the platoon on A's lane 1
QUEUE = [f"q{k:02d}" for k in range(54)]  # commanded cars behind it, 9 m apart
EGO_MAX = 5.0  # the commanded car on A's ending lane 0 from 50 m: its vType's maxSpeed


def _drop_files(folder: Path) -> tuple[Path, Path]:
    """A (2 lanes, 600 m, 25 m/s) -> B (1 lane, 400 m): A's lane 1 goes on as B's lane 0,
    A's lane 0 ends. A slow SUMO car (4 m/s) on lane 1 at 590 m, 54 cars at 4 m/s behind it
    from 100 m, 9 m apart (a dense platoon), the ego on lane 0 at 300 m at 4 m/s,
    ``EGO_MAX`` at most (its plain reach 5 x 10 x 2 + 2 x 7.5 = 115 m)."""
    net = lane_drop_net(folder)
    slow = (
        '<vType id="slow" length="5" minGap="2.5" maxSpeed="4" sigma="0" '
        'lcCooperative="0" lcSpeedGain="0"/>'
    )
    crawl = (
        '<vType id="crawl" length="5" minGap="2.5" accel="2.6" decel="4.5" sigma="0" '
        f'maxSpeed="{EGO_MAX}"/>'
    )
    heads = "\n".join(
        f'    <vehicle id="{v}" type="slow" route="r" depart="0" '
        f'departPos="{590 + 20 * k}" departSpeed="4" departLane="1"/>'
        for k, v in enumerate(SLOW)
    )
    queue = "\n".join(
        f'    <vehicle id="{v}" type="car" route="r" depart="0" departLane="1" '
        f'departPos="{100 + 9 * k}" departSpeed="0"/>'
        for k, v in enumerate(QUEUE)
    )
    routes = folder / "drop.rou.xml"
    routes.write_text(
        f'<routes>\n    {CAR}\n    {slow}\n    {crawl}\n    <route id="r" edges="A B"/>\n'
        f'{heads}\n{queue}\n    <vehicle id="ego" type="crawl" route="r" depart="0" '
        f'departLane="0" departPos="300" departSpeed="4"/>\n</routes>\n'
    )
    return net, routes


def test_usable_distance_and_continuations(tmp_path: Path) -> None:
    """LC2013's JAM_FACTOR is 1: 550 m ahead with 300 m occupied leaves 250 m, below the
    reach at 15 m/s to the left (15 x 10 x 2 + 2 x 7.5 = 315 m) where 550 m is not; on
    the drop, A's lane 1 continues on B's lane 0, the ending lane 0 and B's lane on
    nothing in the section."""
    assert JAM_FACTOR == 1.0
    reach = strategic_reach_m(np.array([1]), np.array([15.0]), np.array([7.5]))
    np.testing.assert_allclose(reach, [315.0])
    usable = usable_distance_m(np.array([550.0, 550.0]), np.array([300.0, 0.0]))
    np.testing.assert_allclose(usable, [250.0, 550.0])
    assert usable[0] < reach[0] < usable[1]
    net, _ = _drop_files(tmp_path)
    section = read_section(net, ["A", "B"], False)
    chains = continuation_lanes(section)
    assert chains == {"A_0": (), "A_1": ("B_0",), "B_0": ()}, chains
    # Occupation acts on the ending lane A_0 and the junction's internal lanes, not on the
    # lanes that carry on (A_1 onto B_0, and B_0, the open section's last edge).
    drop = drop_chain_lanes(section)
    assert "A_0" in drop and not drop & {"A_1", "B_0"}, drop
    assert all(lane == "A_0" or lane.startswith(":") for lane in drop), drop


@pytest.fixture(scope="module")
def drops(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """Per ``deploy.merge_reach`` ("plain": the hand-over at the plain reach, the yield to
    handed-over cars' blockers; "occupation": at LC2013's usable distance, the yield to the
    blockers of every car that must leave its lane), the drop with every car but the slow one
    commanded by a policy cloned from IDM (desired 25 m/s), 120 s: the ego's distance to its lane's
    end and reach when first handed over, where it left lane 0, the yields (commanded cars
    that took SUMO's slow-down, per step) and the collisions and teleports."""
    folder = tmp_path_factory.mktemp("lane_drop")
    net, routes = _drop_files(folder)
    base = small_section_scenario(
        folder, net, routes, ["A", "B"], instrumented={"ids": SLOW},
        simulation={"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 2},
    )  # fmt: skip
    section = read_section(net, ["A", "B"], False)
    act = policy_batch(idm_agent("lookahead", 25.0))
    out: dict[str, dict] = {}
    for name, on in (("plain", False), ("occupation", True)):
        reach = "occupation" if on else "plain"
        d = dataclasses.replace(base.deploy, merge="sumo", merge_reach=reach)
        drv = Recording(dataclasses.replace(base, deploy=d), section, 0, act, "sumo")
        assert drv.occupation is on and drv.yield_all is on
        sc = drv.sc
        opts = SumoOptions(net, (), sc.simulation.step_length_s, sc.seed, route_files=(routes,))
        sim = Simulation(dataclasses.replace(opts, user_demand=True))
        left_at = None
        try:
            for _ in range(int(120.0 / sc.simulation.step_length_s)):
                drv.before_step(sim)
                sim.step()
                st = sim.vehicle_states()
                if left_at is None and "ego" in st.index and st.lanes[st.index["ego"]] != "A_0":
                    left_at = float(drv.last_ego_pos)
            collisions, teleports = sim.collisions(), sim.teleports()
        finally:
            sim.close()
        out[name] = {
            "handed": drv.ego_handed,
            "left_at": left_at,
            "yields": drv.yields_taken,
            "collisions": collisions,
            "teleports": teleports,
        }
    return out


class Recording(SectionSpeedDriver):
    """``SectionSpeedDriver`` that records the ego's first hand-over (its distance to the
    lane's end and its plain reach then), its last position on lane 0 and the yields."""

    ego_handed: tuple[float, float] | None = None
    last_ego_pos = float("nan")
    yields_taken = 0

    def merges(self, sim, vids, ahead_m, reach_m):  # type: ignore[no-untyped-def]
        keep = super().merges(sim, vids, ahead_m, reach_m)
        if self.ego_handed is None and "ego" in self.merging:
            i = vids.index("ego")
            self.ego_handed = (float(self._raw_ahead[i]), float(reach_m[i]))
        return keep

    def usable_m(self, ahead_m, rows, lanes, slots, st):  # type: ignore[no-untyped-def]
        self._raw_ahead = ahead_m
        if "ego" in st.index and st.lanes[st.index["ego"]] == "A_0":
            self.last_ego_pos = float(st.pos_m[st.index["ego"]])
        return super().usable_m(ahead_m, rows, lanes, slots, st)

    def yields(self, sim, vids, near, speed, safe):  # type: ignore[no-untyped-def]
        cap = super().yields(sim, vids, near, speed, safe)
        self.yields_taken += int(np.count_nonzero(np.isfinite(cap)))
        return cap


def test_the_hand_over_starts_before_the_plain_reach_in_a_queue(drops: dict[str, dict]) -> None:
    """With the occupation the ego is handed over with more than its plain reach left
    (LC2013's usable distance: the platoon ahead on the through lane and on B) and gets
    into the platoon; without it, only within the reach, and it is still on the ending
    lane after 120 s (measured: handed over 296 m before the end, reach 95 m, left lane 0
    at 502 m; plain 113.5 m, reach 115 m, not left)."""
    plain, occ = drops["plain"], drops["occupation"]
    assert occ["handed"] is not None and occ["handed"][0] > occ["handed"][1] + 100.0, occ
    assert plain["handed"] is not None and plain["handed"][0] <= plain["handed"][1], plain
    assert occ["left_at"] is not None, drops
    assert plain["left_at"] is None or occ["left_at"] < plain["left_at"], drops


def test_the_yield_opens_a_gap_collision_free(drops: dict[str, dict]) -> None:
    """The commanded cars on the through lane that block the ego take SUMO's cooperative
    slow-down (yields: 210 commanded vehicle-steps, 152 in the plain variant), and nobody
    collides or teleports in either variant."""
    assert drops["occupation"]["yields"] > 0, drops
    for name, got in drops.items():
        assert got["collisions"] == 0 and got["teleports"] == 0, (name, got)


def test_merge_reach_is_occupation_by_default_and_checked(tmp_path: Path) -> None:
    """``deploy.merge_reach``: "occupation" by default (stop 46), recorded in the scenario's
    dict; "plain" said is left out of it (a run deployed before the default moved keeps its
    digest), the driver's occupation and yield_all on and off. With merge "none" or
    "handover" the default loads as plain (both off); "occupation" said with
    them, or an unknown value, is one line naming file, field and what is accepted."""
    net, routes = _drop_files(tmp_path)
    on = small_section_scenario(tmp_path, net, routes, ["A", "B"])
    assert on.deploy.merge_reach == "occupation"
    assert on.to_dict()["deploy"]["merge_reach"] == "occupation"
    said = small_section_scenario(
        tmp_path, net, routes, ["A", "B"], deploy={"merge_reach": "occupation"}
    )
    assert said.digest() == on.digest()
    plain = small_section_scenario(
        tmp_path, net, routes, ["A", "B"], deploy={"merge_reach": "plain"}
    )
    assert "merge_reach" not in plain.to_dict()["deploy"] and plain.digest() != on.digest()
    section = read_section(net, ["A", "B"], False)
    for sc, want in ((plain, False), (on, True)):
        drv = SectionSpeedDriver(sc, section, 0, None, "sumo")  # type: ignore[arg-type]
        assert drv.occupation is want and drv.yield_all is want
    for merge in ("none", "handover"):  # the implicit default: accepted, loads as plain
        sc = small_section_scenario(tmp_path, net, routes, ["A", "B"], deploy={"merge": merge})
        assert sc.deploy.merge_reach == "plain" and sc.deploy.merge == merge
        drv = SectionSpeedDriver(sc, section, 0, None, "sumo")  # type: ignore[arg-type]
        assert drv.occupation is False and drv.yield_all is False
    for bad, msg_has in (
        ({"merge_reach": "always"}, "'plain', 'occupation'"),
        ({"merge_reach": "occupation", "merge": "handover"}, "deploy.merge = 'sumo'"),
        ({"merge_reach": "occupation", "merge": "none"}, "accepted with deploy.merge = 'none'"),
    ):
        with pytest.raises(UserError) as err:
            small_section_scenario(tmp_path, net, routes, ["A", "B"], deploy=bad)
        msg = str(err.value)
        assert "\n" not in msg and "s.toml" in msg and "deploy.merge_reach" in msg, msg
        assert msg_has in msg, msg

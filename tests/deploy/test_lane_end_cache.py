"""The one lane-end cache of a speed-commanding driver (``deploy.slots.VehicleSlots.lane_end``):
the driven vehicles' lane ends (``SectionSpeedDriver.lane_end_m``) and those of the vehicles
not driven that ``MergeYield.must_change`` asks about (``deploy.merge_reach =
"occupation"``) share it, keyed by vehicle, and a vehicle not driven that left the section
is dropped from it, as a driven one is on its release."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from conftest import small_section_scenario
from deploy_nets import CAR, idm_agent, lane_drop_net

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.deploy.slots import NOT_ASKED
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions


class Watching(SectionSpeedDriver):
    """Records, per ``must_change`` call, whether SUMO's car "s0" was among the vehicles
    that must change and its entry in the lane-end cache then (lane code, offset)."""

    seen: list[tuple[bool, bool, int, float]]

    def must_change(self, sim, vids, slots, st):  # type: ignore[no-untyped-def]
        out = super().must_change(sim, vids, slots, st)
        at = self.slots.of.get("s0")
        cache = self.slots.lane_end
        entry = (NOT_ASKED, 0.0) if at is None else (int(cache.lane[at]), float(cache.offset[at]))
        self.seen.append(("s0" in out, "s0" in self.others, *entry))
        return out


def test_a_vehicle_not_driven_shares_the_cache_and_is_dropped_when_it_left(
    tmp_path: Path,
) -> None:
    """A (2 lanes, 300 m) -> B (1 lane, 300 m), A's lane 0 ends: SUMO's own car "s0" (the
    instrumented one) starts on it and must change left (offset 1, in ``must_change``), its
    entry in the driven vehicles' cache; commanded cars depart every 3 s until 72 s, so the
    driver is called after "s0" left B. Then its entry is gone (``NOT_ASKED``, not in
    ``others``), where the per-vehicle dictionary before kept every vehicle it met."""
    net = lane_drop_net(tmp_path, 300.0, 300.0)
    routes = tmp_path / "r.rou.xml"
    cars = "\n".join(
        f'    <vehicle id="c{k}" type="car" route="r" depart="{3 * k}" departLane="1" '
        'departSpeed="5"/>'
        for k in range(25)
    )
    routes.write_text(
        f'<routes>\n    {CAR}\n    <route id="r" edges="A B"/>\n'
        '    <vehicle id="s0" type="car" route="r" depart="0" departLane="0" departPos="20" '
        f'departSpeed="10"/>\n{cars}\n</routes>\n'
    )
    base = small_section_scenario(
        tmp_path, net, routes, ["A", "B"], instrumented={"ids": ["s0"]},
        simulation={"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 1},
        deploy={"merge_reach": "occupation"},
    )  # fmt: skip
    sc = dataclasses.replace(base, deploy=dataclasses.replace(base.deploy, merge="sumo"))
    section = read_section(net, ["A", "B"], False)
    drv = Watching(sc, section, 0, policy_batch(idm_agent("lookahead", 25.0)), "sumo")
    drv.seen = []
    opts = SumoOptions(net, (), sc.simulation.step_length_s, sc.seed, route_files=(routes,))
    sim = Simulation(dataclasses.replace(opts, user_demand=True))
    try:
        for _ in range(int(80.0 / sc.simulation.step_length_s)):
            drv.before_step(sim)
            sim.step()
    finally:
        sim.close()
    assert drv.yield_all and drv.seen, drv.seen
    a0 = drv.lane_table.codes(["A_0"])[0]
    # While on A's ending lane: in must_change, its entry the lane end's (lane A_0, offset 1).
    on_a0 = [s for s in drv.seen if s[2] == a0]
    assert on_a0 and all(s[0] and s[1] and s[3] == 1.0 for s in on_a0), drv.seen
    # It left the section before the last calls: dropped from the cache and from others.
    assert drv.seen[-1] == (False, False, NOT_ASKED, 0.0), drv.seen[-5:]
    slot = drv.slots.of["s0"]
    assert (
        drv.slots.lane_end.lane[slot] == NOT_ASKED and drv.slots.lane_end.again[slot] == -math.inf
    )
    assert "s0" not in drv.others

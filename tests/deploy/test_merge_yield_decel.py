"""The merge yield (``deploy.merge = "sumo"``, ``MergeYield.yields``) brakes a commanded
vehicle no harder than its vType's decel. Its cap is SUMO's own speed of the last step
(getSpeedWithoutTraCI), chosen from the speed the vehicle had then: where the policy
accelerated in between, that speed asked of it now is a braking beyond its decel, which a
follower SUMO drives (a merging or an instrumented one) does not plan for. On drawn 501
(``driver_follow = "drawn"``, occupation, seed 501, run 1, at 8d50d39) a commanded car on
m1's through lane was yielded from 3.36 to 0 m/s in one step (6.7 m/s^2, decel 4.5), and
the car that had just merged in 0.11 m behind it, handed over to SUMO, hit it at 0.55 m/s."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from conftest import small_section_scenario
from deploy_nets import idm_agent
from test_lane_drop_occupation import SLOW, _drop_files

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions


class Yields(SectionSpeedDriver):
    """Records each yield taken: (the vehicle's speed, its decel, the cap)."""

    taken: list[tuple[float, float, float]]

    def yields(self, sim, vids, near, speed, safe):  # type: ignore[no-untyped-def]
        cap = super().yields(sim, vids, near, speed, safe)
        for i in near:
            if np.isfinite(cap[i]):
                self.taken.append((float(speed[i]), self.shape_of[vids[i]][2], float(cap[i])))
        return cap


def test_the_yield_brakes_no_harder_than_the_vehicles_decel(tmp_path: Path) -> None:
    """The lane drop (a dense platoon on the through lane, the ego on the ending lane), every
    car but the slow head commanded by a policy cloned from IDM, merge_reach occupation, 120
    s: every yield's cap is at least v - decel dt (fails before: 1 of 210 yields asked
    more, 6.3 m/s^2 against the cars' 4.5; after, 210 yields, at most 4.5), nobody collides."""
    net, routes = _drop_files(tmp_path)
    base = small_section_scenario(
        tmp_path, net, routes, ["A", "B"], instrumented={"ids": SLOW},
        simulation={"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 2},
    )  # fmt: skip
    d = dataclasses.replace(base.deploy, merge="sumo", merge_reach="occupation")
    sc = dataclasses.replace(base, deploy=d)
    drv = Yields(
        sc,
        read_section(net, ["A", "B"], False),
        0,
        policy_batch(idm_agent("lookahead", 25.0)),
        "sumo",
    )
    drv.taken = []
    dt = sc.simulation.step_length_s
    opts = SumoOptions(net, (), dt, sc.seed, route_files=(routes,))
    sim = Simulation(dataclasses.replace(opts, user_demand=True))
    try:
        for _ in range(int(120.0 / dt)):
            drv.before_step(sim)
            sim.step()
        collisions = sim.collisions()
    finally:
        sim.close()
    got = np.array(drv.taken)
    assert len(got) > 10, len(got)
    asked = (got[:, 0] - got[:, 2]) / dt  # the braking each yield asks [m/s^2]
    over = asked > got[:, 1] + 1e-9
    assert not over.any(), (int(over.sum()), len(got), float(asked.max()))
    assert collisions == 0

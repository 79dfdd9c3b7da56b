"""A prior whose fitted minGap is below the vehicle's own, deployed without the safety
layer: the policy stops at its prior's minGap, inside the vehicle's own, where SUMO counts
a collision (collisionMinGapFactor 1; Stage II's replay counts only an overlap). Drawn net
501 (lookahead_gap, Krauss prior fitted at 2.458 m to a fleet of 2.5 m cars and trucks
and 2.0 m IDM cars): every one of the 475 collision events of its 4 runs with safety
"none" was a car or truck creeping at 0.01-0.08 m/s into the minGap of the standing
vehicle ahead (hC, stop 37). The deployment's observation takes the deficit off the
leader column (``deploy.observe.min_gap_deficit_m``), a standing leader at a red light
included, where the prior ran the light (hD, stop 36). Real SUMO, numpy prior.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import prior_alone
from red_light import CROSS, EDGES, Standing, red_light_queue

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.observe import min_gap_deficit_m
from macromicro_sumo.deploy.run import sampled
from macromicro_sumo.road.section import read_section
from macromicro_sumo.truth.section import record_run


def test_a_prior_below_the_vehicles_min_gap_stops_at_its_own_without_the_layer(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """Four cars (SUMO's default vType, minGap 2.5 m) into a light that stays red, each
    driven by a Krauss prior alone fitted at minGap 2.3 m, safety "none": no collision,
    the first stands before the line, the queue 7.5 m (length + the cars' minGap) apart or
    more. Before: the prior ran the red light (a stop point never read below 0 room: its
    standing leader's gap stayed at 2.5 m) and its followers crept to 2.3 m behind the car
    ahead, SUMO's collisions."""
    sc, sim = red_light_queue(tmp_path, 4, 80.0)
    act = prior_alone({**cross_krauss, "min_gap_m": 2.3})
    assert act.stop_gap_m == pytest.approx(2.3)
    drv = Standing(sc, read_section(CROSS, EDGES, False), 0, act, "none")
    try:
        _, stats = record_run(sim, sc, drv.section, 0, drv)
    finally:
        sim.close()
    assert stats["collisions"] == 0, stats
    dist = np.array([drv.at[f"v{i}"][0] for i in range(4)])
    speed = np.array([drv.at[f"v{i}"][1] for i in range(4)])
    assert (speed < 0.1).all(), speed
    assert 0.0 < dist[0] < 1.5, dist
    assert (np.diff(dist) > 7.5 - 1e-3).all(), dist


def test_the_deficit_is_the_own_min_gap_beyond_the_stop_gap() -> None:
    """Only a vehicle whose minGap exceeds the policy's stop gap observes less room; a
    sampled action keeps its mean's stop gap."""
    got = min_gap_deficit_m(np.array([2.5, 2.0, 2.458]), 2.458)
    np.testing.assert_allclose(got, [0.042, 0.0, 0.0], atol=1e-12)
    act = prior_alone({"speed_factor": 1.0, "accel_mps2": 2.6, "decel_mps2": 4.5,
                       "tau_s": 1.0, "min_gap_m": 2.4, "veh_length_m": 5.0, "dt_s": 0.5,
                       "relax_s": 0.0})  # fmt: skip
    assert sampled(act, 0.3, np.random.default_rng(0)).stop_gap_m == pytest.approx(2.4)


class Columns(SectionSpeedDriver):
    """The deployment's driver, also keeping the leader column less SUMO's gap of every
    driven vehicle behind a vehicle (the "lookahead" layout: own minGap + leader length)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.extra: list[float] = []

    def observe(self, sim, vids, rows, st, *args, **kwargs):
        obs, gap, decel, lead = super().observe(sim, vids, rows, st, *args, **kwargs)
        near = gap < 100.0
        self.extra += (obs[near, 2] - gap[near]).tolist()
        return obs, gap, decel, lead


@pytest.mark.parametrize(("safety", "extra"), [("sumo", 7.5), ("none", 7.3)])
def test_only_a_deployment_without_the_layer_observes_the_deficit(
    tmp_path: Path, cross_krauss: dict, safety: str, extra: float
) -> None:
    """With the safety layer, which holds each vehicle at its own minGap (SUMO's safe speed
    on SUMO's gap), the policy observes what Stage II trained on: the leader column is
    SUMO's gap + the car's minGap 2.5 + the leader's length 5. Without it, 0.2 m less
    (the prior's 2.3). Before, both read 7.3: on Bremen (prior 2.397 m, cars 2.5 m) the
    layer-on deployment's speed RMSE went 1.146 -> 1.217 m/s over 4 runs."""
    sc, sim = red_light_queue(tmp_path, 3, 40.0)
    act = prior_alone({**cross_krauss, "min_gap_m": 2.3})
    drv = Columns(sc, read_section(CROSS, EDGES, False), 0, act, safety)
    try:
        record_run(sim, sc, drv.section, 0, drv)
    finally:
        sim.close()
    assert len(drv.extra) > 20
    np.testing.assert_allclose(drv.extra, extra, atol=1e-9)

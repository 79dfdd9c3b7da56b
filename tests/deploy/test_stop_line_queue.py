"""Where a deployed prior's queue stands at a red light: where SUMO's own drivers stand.

SUMO's drivers stop jmStoplineGap (1 m, its default) before a red line and keep no minGap
to it; the observation's standing leader (``road.leaders.standing_spacing_m``) sits minGap
beyond that stop, so a prior keeping its minGap to it stops there too. Before, its back was
at the line and the prior (game/cross's Krauss fit, minGap 2.49 m) stopped 2.2 m before it:
the queue stood 1.2 m upstream of the truth's, and a loop 36 m before the line read a car
standing on it (hU, stop 34).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import netconvert, one_phase_program, prior_alone, small_section_scenario
from red_light import CROSS, EDGES, Standing, red_light_queue

from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run


def test_the_prior_alone_stands_where_sumo_stands_at_a_red_light(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """Three cars from 1fi to 2fo, every one driven by the prior alone (residual 0, the
    deployment's safety layer), the light red all along: the first stands 1.0 +- 0.2 m
    before 1si's stop line, as SUMO's own drivers (1.00 m), the next ones 7.5 m apart, as
    SUMO's queue. Before: 2.2 m (the prior's min gap to a leader whose back is at the line,
    less its overshoot). Without the safety layer it stands 0.71 m before the line (the
    prior's approach overshoots by 0.3 m, as it did before)."""
    sc, sim = red_light_queue(tmp_path, 3, 80.0)
    drv = Standing(sc, read_section(CROSS, EDGES, False), 0, prior_alone(cross_krauss), "sumo")
    try:
        _, stats = record_run(sim, sc, drv.section, 0, drv)
    finally:
        sim.close()
    assert stats["collisions"] == 0
    dist = np.array([drv.at[f"v{i}"][0] for i in range(3)])
    speed = np.array([drv.at[f"v{i}"][1] for i in range(3)])
    assert (speed < 0.1).all(), speed
    assert abs(dist[0] - 1.0) < 0.2, dist
    np.testing.assert_allclose(np.diff(dist), 7.5, atol=0.3)


# A vType that stops 3 m before a red line and keeps 4 m to a leader (SUMO's Krauss).
FAR = '<vType id="far" length="5" minGap="4" jmStoplineGap="3" sigma="0" speedDev="0"/>'


def test_the_deployment_stops_where_sumo_stops_a_vtype_with_its_own_stopline_gap(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """One "far" car (jmStoplineGap 3 m, minGap 4 m) from A (300 m, one lane) into a light
    that stays red: driven by the deployment's driver (the prior alone with the far type's
    minGap, residual 0, the safety layer), it stands where SUMO's own driver of that vType
    stands, 3.0 m before the line (within 0.15 m). Before (the driver's red line less
    SUMO's default 1 m, whatever the vType): 1.0 m before it."""
    nodes = '<node id="n0" x="0" y="0"/><node id="tl" x="300" y="0" type="traffic_light"/>'
    edges = (
        '<edge id="A" from="n0" to="tl" numLanes="1" speed="15"/>'
        '<edge id="B" from="tl" to="n2" numLanes="1" speed="15"/>'
    )
    net = netconvert(tmp_path, nodes + '<node id="n2" x="500" y="0"/>', edges)
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        f"<routes>\n    {FAR}\n"
        '    <vehicle id="v0" type="far" depart="0" departSpeed="10" departPos="50">'
        '<route edges="A B"/></vehicle>\n</routes>\n'
    )
    red = one_phase_program(tmp_path, "tl", "r")
    sc = small_section_scenario(tmp_path, net, routes, ["A", "B"], instrumented={"ids": ["probe"]})
    opts = SumoOptions(net, (red,), 0.5, 5, route_files=(routes,), user_demand=True)
    sim = Simulation(opts)
    try:  # SUMO's own driver of the far type
        for _ in range(120):
            sim.step()
        sumo_stop = sim.stop_line_m("v0")
        assert sim.vehicle_states().speed_mps[0] < 0.01
    finally:
        sim.close()
    assert abs(sumo_stop - 3.0) < 0.05, sumo_stop
    section = read_section(net, ["A", "B"], False)
    drv = Standing(sc, section, 0, prior_alone({**cross_krauss, "min_gap_m": 4.0}), "sumo")
    sim = Simulation(opts)
    try:
        _, stats = record_run(sim, sc, drv.section, 0, drv)
    finally:
        sim.close()
    assert stats["collisions"] == 0
    dist, speed = drv.at["v0"]
    assert speed < 0.1, speed
    assert abs(dist - sumo_stop) < 0.15, (dist, sumo_stop)

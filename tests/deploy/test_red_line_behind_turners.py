"""A long vehicle waiting at a red light while side-street cars turn in just past the line:
the deployment keeps the red line as its standing leader (``deploy.observe.observe_rows``,
``road.leaders.nearer_standing`` by SUMO's gaps, the leader's own length).

Before, the red line and SUMO's leader were compared as front-to-front spacings, the line a
standing vehicle of the own length: a truck (12 m) took a car (5 m) that stood or moved
less than 7 m past its stop as the nearer, lost the line and crept up to it, where SUMO's
red-light braking held it on the stop-line loop through the red (arterial 521: 5 of the 7
trucks at the head of a queue stood at the line, SUMO's at 1.0 m; docs/deploy-log.md, "Arterial
521: where the policy's extra error lies (stop 40, hA)").
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from conftest import netconvert, prior_alone, small_section_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run

TRUCK = '<vType id="truck" length="12" minGap="2.5" vClass="truck" maxSpeed="25"/>'
CAR = '<vType id="car" length="5" minGap="2.5"/>'


def _turners(folder: Path) -> tuple:
    """A (300 m, one lane) -> light "tl" -> B (200 m); S (200 m) from the south onto B at
    the light. A is red and S green all along: one truck on A waits at the line while a
    car from S turns onto B every 3 s from 10 s on."""
    nodes = (
        '<node id="n0" x="0" y="0"/><node id="tl" x="300" y="0" type="traffic_light"/>'
        '<node id="n2" x="500" y="0"/><node id="s0" x="300" y="-200"/>'
    )
    edges = (
        '<edge id="A" from="n0" to="tl" numLanes="1" speed="15"/>'
        '<edge id="B" from="tl" to="n2" numLanes="1" speed="15"/>'
        '<edge id="S" from="s0" to="tl" numLanes="1" speed="15"/>'
    )
    net = netconvert(folder, nodes, edges)
    state = ["r"] * 8
    for c in ET.parse(net).getroot().iter("connection"):
        if c.get("tl") == "tl" and c.get("from") == "S":
            state[int(c.get("linkIndex"))] = "G"
    n = 1 + max(
        int(c.get("linkIndex")) for c in ET.parse(net).getroot().iter("connection") if c.get("tl")
    )
    program = folder / "side.add.xml"
    program.write_text(
        '<additional>\n    <tlLogic id="tl" type="static" programID="side" offset="0">\n'
        f'        <phase duration="10000" state="{"".join(state[:n])}"/>\n'
        "    </tlLogic>\n</additional>\n"
    )
    routes = folder / "r.rou.xml"
    cars = "".join(
        f'    <vehicle id="c{i}" type="car" depart="{10 + 3 * i}" departSpeed="10">'
        '<route edges="S B"/></vehicle>\n'
        for i in range(12)
    )
    routes.write_text(
        f"<routes>\n    {TRUCK}\n    {CAR}\n"
        '    <vehicle id="truck" type="truck" depart="0" departSpeed="10" departPos="150">'
        '<route edges="A B"/></vehicle>\n'
        f"{cars}</routes>\n"
    )
    sc = small_section_scenario(
        folder, net, routes, ["A", "B"], instrumented={"ids": ["probe"]},
        simulation={"warmup_s": 0.0, "duration_s": 50.0, "n_runs": 2},
        detectors={"interval_s": 25.0}, deploy={"safety_floor_on": "standing"},
    )  # fmt: skip
    opts = SumoOptions(net, (program,), 0.5, 5, route_files=(routes,), user_demand=True)
    return sc, net, opts


def test_a_truck_keeps_its_stop_at_a_red_line_as_cars_turn_in_past_it(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """SUMO's own truck stands 1.0 m before the red line while the side street's cars turn
    onto B in front of it. Driven by the prior alone (residual 0, the safety layer) it
    stands there too (within 0.2 m) all along, 0 collisions. Before: at the line (0.0 m),
    from the first car turning in."""
    sc, net, opts = _turners(tmp_path)
    section = read_section(net, ["A", "B"], False)
    sim = Simulation(opts)
    try:
        own, _ = record_run(sim, sc, section, 0)
    finally:
        sim.close()
    drv = SectionSpeedDriver(sc, section, 0, prior_alone(cross_krauss), "sumo")
    sim = Simulation(opts)
    try:
        deployed, stats = record_run(sim, sc, section, 0, drv)
    finally:
        sim.close()
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    ends = {}
    for name, df in (("own", own), ("deployed", deployed)):
        truck = df[(df["vehicle_id"] == "truck") & (df["time_s"] > 30.0)]
        assert (truck["speed_mps"] < 0.1).all(), (name, truck)
        ends[name] = truck["arc_m"].to_numpy()
    assert ends["own"].size and np.allclose(ends["own"], ends["own"][0]), ends
    assert (np.abs(ends["deployed"] - ends["own"][0]) < 0.2).all(), ends

"""The deployment stops a driven car where SUMO's driver of it stops at a red light, on
every lane: one routed through on a turning lane, and a lane with a stopOffset.

SUMO's getNextTLS gives a car whose lane does not lead its way the red of the link it
should take (game/cross: a car routed through on 1si's right-turn lane 0 gets the through
link 7's, from 1si_1); SUMO's driver of it stops 0 m before its lane's end, not its
jmStoplineGap before the line (``Simulation.stop_lines``' ``own``). At a lane with a
stopOffset SUMO's driver stands max(jmStoplineGap, stopOffset) before the line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sumo
import sumolib
from conftest import (
    cross_program,
    one_phase_program,
    prior_alone,
    small_section_scenario,
    stop_offset_net,
)

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


class LaneEnds(SectionSpeedDriver):
    """The deployment's driver with lane changes off, keeping each driven vehicle's
    distance to its lane's end and speed at its last step."""

    def __init__(self, lengths: dict[str, float], *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.lengths, self.at = lengths, {}

    def drive(self, sim, vids, st) -> None:
        sim.set_lane_change_mode(vids, 0)
        super().drive(sim, vids, st)
        lanes, pos, speed = sim.lane_states(vids)
        for v, ln, p, s in zip(vids, lanes, pos, speed, strict=True):
            self.at[v] = (self.lengths[ln] - float(p), float(s))


class SumoLaneEnds:
    """SUMO drives everyone, lane changes off; each vehicle's last distance to its lane's
    end and speed."""

    def __init__(self, lengths: dict[str, float]) -> None:
        self.lengths, self.at = lengths, {}

    def before_step(self, sim: Simulation) -> None:
        st = sim.vehicle_states()
        sim.set_lane_change_mode(list(st.ids), 0)
        for v, ln, p, s in zip(st.ids, st.lanes, st.pos_m, st.speed_mps, strict=True):
            self.at[v] = (self.lengths[ln] - float(p), float(s))


def stands(
    folder: Path, net: Path, add: Path, routes: Path, edges: list[str], prior: dict,
    merge: str = "sumo",
):  # fmt: skip
    """{vehicle: (distance to its lane's end, speed)} at the last step, SUMO's own drivers
    and the deployment's (the prior alone: residual 0, SUMO's safety layer, ``merge``)."""
    sc = small_section_scenario(
        folder, net, routes, edges, instrumented={"ids": ["probe"]}, deploy={"merge": merge}
    )
    opts = SumoOptions(net, (add,), 0.5, 5, route_files=(routes,), user_demand=True)
    lanes = sumolib.net.readNet(str(net), withInternal=True).getEdges(withInternal=True)
    lengths = {ln.getID(): ln.getLength() for e in lanes for ln in e.getLanes()}
    out = []
    for driver in ("sumo", "deployment"):
        section = read_section(net, edges, False)
        drv = (
            SumoLaneEnds(lengths)
            if driver == "sumo"
            else LaneEnds(lengths, sc, section, 0, prior_alone(prior), "sumo")
        )
        sim = Simulation(opts)
        try:
            _, stats = record_run(sim, sc, section, 0, drv)
        finally:
            sim.close()
        assert stats["collisions"] == 0
        out.append(drv.at)
    return out


@pytest.mark.parametrize("merge", ["none", "sumo"])
def test_a_car_on_a_lane_that_does_not_lead_its_way_stops_at_the_lanes_end(
    tmp_path: Path, cross_krauss: dict, merge: str
) -> None:
    """game/cross with link 7 (1si_1, through) red and link 6 (1si_0, right) green: "thr",
    routed through on 1si_0 (lane changes off), and "one", through on 1si_1. SUMO's driver
    stands thr 0.00 m before its lane's end, one 1.00 m before the line. The deployment's
    driver (game/cross's Krauss prior alone) stands each where SUMO does (within 0.15 m).
    Before, with ``deploy.merge = "none"``: thr 1.0 m before the end (the through link's
    red less 1 m); with "sumo" (the default) thr is handed to SUMO's model there, as
    before."""
    add = cross_program(tmp_path, green=(6,))
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        "<routes>\n"
        '    <vehicle id="thr" depart="0" departSpeed="10" departLane="0" departPos="20">'
        '<route edges="1si 2o 2fo"/></vehicle>\n'
        '    <vehicle id="one" depart="0" departSpeed="10" departLane="1" departPos="20">'
        '<route edges="1si 2o 2fo"/></vehicle>\n</routes>\n'
    )
    edges = ["1fi", "1si", "2o", "2fo"]
    sumo_at, deployed = stands(tmp_path, CROSS, add, routes, edges, cross_krauss, merge)
    for v, want in (("thr", 0.0), ("one", 1.0)):
        assert sumo_at[v][1] < 0.01 and abs(sumo_at[v][0] - want) < 0.05, sumo_at
        assert deployed[v][1] < 0.1, deployed
        assert abs(deployed[v][0] - sumo_at[v][0]) < 0.15, (v, deployed[v], sumo_at[v])


def test_the_deployment_stops_before_a_lanes_stop_offset(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """A (300 m, 2 lanes) into a light that stays red, with a stopOffset of 3 m on A and
    of 6 m on lane 1 for passenger cars: SUMO's drivers (jmStoplineGap 1 m) stand 3.00 m
    before the line on lane 0 and 6.00 m on lane 1; the deployment's driver (the prior
    alone) stands each where SUMO does (within 0.15 m). Before: 1.0 m before the line."""
    net = stop_offset_net(tmp_path)
    add = one_phase_program(tmp_path, "tl", "rrrr")
    routes = tmp_path / "r.rou.xml"
    cars = "".join(
        f'    <vehicle id="v{k}" depart="0" departSpeed="10" departLane="{k}" departPos="50">'
        '<route edges="A B"/></vehicle>\n'
        for k in (0, 1)
    )
    routes.write_text(f"<routes>\n{cars}</routes>\n")
    sumo_at, deployed = stands(tmp_path, net, add, routes, ["A", "B"], cross_krauss)
    for v, want in (("v0", 3.0), ("v1", 6.0)):
        assert sumo_at[v][1] < 0.01 and abs(sumo_at[v][0] - want) < 0.05, sumo_at
        assert deployed[v][1] < 0.1, deployed
        assert abs(deployed[v][0] - sumo_at[v][0]) < 0.15, (v, deployed[v], sumo_at[v])
    assert np.isfinite([deployed[v][0] for v in ("v0", "v1")]).all()

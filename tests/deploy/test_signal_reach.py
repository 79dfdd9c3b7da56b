"""Stop lines asked only on lanes from which a signal can be reached
(``sumo.signal_reach.signal_lanes``, ``SectionSpeedDriver.observe``): SUMO's getNextTLS has
nothing to say elsewhere, so the deployment is the same without the question."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import sumo
from conftest import ROOT, prior_alone, small_section_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.signal_reach import signal_lanes
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run

CROSS_DIR = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross"
CROSS = CROSS_DIR / "cross.net.xml"
EDGES = ["1fi", "1si", "2o", "2fo"]


def test_the_lanes_that_can_reach_a_signal() -> None:
    """game/cross: the approaches to its one signal (each arm's fi and si lanes) and the
    internal lanes between them, not the exits (o, fo) nor the signalised junction's own
    internal lanes (past the line). Bremen: none of the section's lanes reaches the ramp's
    signal. netgen_corridor has no signal."""
    cross = signal_lanes(CROSS)
    arms = {f"{a}{k}" for a in "1234" for k in ("fi", "si")}
    assert {ln.rpartition("_")[0] for ln in cross if not ln.startswith(":")} == arms
    assert not any(ln.startswith(":0_") for ln in cross)
    assert {":m1_1_0", ":m2_0_0"} <= cross
    bremen = signal_lanes(ROOT / "sumo_nets" / "highway_bremen" / "highway.net.xml")
    section = ["145354574", "189597495", "E0", "191842213"]
    assert bremen and not any(ln.rpartition("_")[0] in section for ln in bremen)
    assert "201283198_0" in bremen  # the signal's own approach
    assert signal_lanes(ROOT / "sumo_nets" / "netgen_corridor" / "corridor.net.xml") == set()


class Asked(SectionSpeedDriver):
    """The deployment's driver, recording the lane of every vehicle SUMO is asked the stop
    line of and every speed command; ``always``: asked whatever the lanes (as before)."""

    def __init__(self, *args, always: bool = False, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.always, self.asked, self.commands = always, [], []

    def drive(self, sim, vids, st) -> None:
        if self.always and self.has_lights:
            self.signal_lanes = frozenset(self.section.lanes)
        seen, lines = [], sim.stop_lines_m
        original = sim.set_speeds
        sim.set_speeds = lambda v, c: (seen.append((tuple(v), np.array(c))), original(v, c))
        sim.stop_lines_m = lambda v: (
            self.asked.extend(st.lanes[st.index[x]] for x in v),
            lines(v),
        )[1]
        try:
            super().drive(sim, vids, st)
        finally:
            del sim.set_speeds, sim.stop_lines_m
        self.commands += seen


def _run(tmp_path: Path, cross_krauss: dict, always: bool) -> Asked:
    text = (CROSS_DIR / "cross.rou.xml").read_text()
    text = re.sub(r'period="(\d+)"', lambda m: f'period="{int(m.group(1)) / 3:g}"', text)
    tmp_path.mkdir()
    routes = tmp_path / "r.rou.xml"
    routes.write_text(text)
    sc = small_section_scenario(
        tmp_path, CROSS, routes, EDGES, simulation={"warmup_s": 0.0, "duration_s": 150.0}
    )
    drv = Asked(
        sc, read_section(CROSS, EDGES, False), 0, prior_alone(cross_krauss), "sumo", always=always
    )
    sim = Simulation(SumoOptions(CROSS, (), 0.5, 5, route_files=(routes,), user_demand=True))
    try:
        record_run(sim, sc, drv.section, 0, drv)
    finally:
        sim.close()
    return drv


def test_vehicles_past_the_signal_are_not_asked_and_drive_the_same(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """game/cross with its own cycling program, the stock demand three times as dense,
    1fi 1si 2o 2fo driven by the Krauss prior: the vehicles on 2o and 2fo (past the
    signal) are never asked for a stop line, those before it are, on every lane change
    onto a new lane; the speed commands are bit for bit those of a driver that asks every
    lane (before: 2o's and 2fo's vehicles were asked too)."""
    new = _run(tmp_path / "new", cross_krauss, always=False)
    old = _run(tmp_path / "old", cross_krauss, always=True)
    edges = {ln.rpartition("_")[0] for ln in new.asked}
    assert edges and edges <= {"1fi", "1si", ":m1_1"}, edges
    assert {ln.rpartition("_")[0] for ln in old.asked} & {"2o", "2fo"}
    assert len(new.commands) == len(old.commands) > 100
    for (v_new, c_new), (v_old, c_old) in zip(new.commands, old.commands, strict=True):
        assert v_new == v_old and c_new.tobytes() == c_old.tobytes()

"""``StopLineReader.decide_green`` (``deploy.green = "switch"``): a red link whose light turns
green at the start of the coming step is no stop now, as SUMO's own drivers move off in the
step the light switches in; read as it shows, a driven queue's head stood a step longer at
every green (drawn 1706). Scripted answers, then a real SUMO light."""

from __future__ import annotations

from pathlib import Path

import libsumo
import numpy as np
from test_yellow_onset import DT, Scripted

from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.sumo.stop_lines import StopLineReader, Upcoming

from conftest import light_queue  # isort: skip


def _reader(s: Scripted, upcoming: dict[str, str | None] | None) -> StopLineReader:
    reader = s.reader()
    if upcoming is not None:
        reader.decide_green(upcoming.get)
    return reader


def test_a_red_that_turns_green_in_the_coming_step_is_no_stop() -> None:
    """Red now at j1 (30 m) and j2 (230 m): j1 green from the coming step -> the line ahead
    is j2's; j1 staying red (or turning red-yellow) is a stop; without ``decide_green``
    j1 is a stop whatever comes."""
    s = Scripted()
    s.state, s.d = "r", 30.0
    assert _reader(s, {"j1": "G", "j2": None}).stop_line("car")[0] == 230.0
    assert _reader(s, {"j1": None, "j2": None}).stop_line("car")[0] == 30.0
    assert _reader(s, {"j1": "u", "j2": None}).stop_line("car")[0] == 30.0
    assert _reader(s, None).stop_line("car")[0] == 30.0
    s.state = "u"  # red-yellow now, green from the coming step: no stop either
    assert _reader(s, {"j1": "g", "j2": "g"}).stop_line("car")[0] == np.inf


def _red_then_green(folder: Path) -> SumoOptions:
    """A (200 m) -> a light, red 20 s then green -> B; 6 Krauss cars queue at the red."""
    return light_queue(folder, 6, 2.0, ((20, "r"), (100, "G")), 'sigma="0" decel="4.5"', DT)


def test_at_a_real_light_the_green_is_met_in_its_switch_step(tmp_path: Path) -> None:
    """Red 20 s, then green: the head's stop line is gone on exactly the step before the
    light shows green (t = 20.0 s, the switch's step), the step in which SUMO's own head
    moves off (its speed after it above 0); the reader without ``decide_green`` still
    says the line then (the scripted test)."""
    sim = Simulation(_red_then_green(tmp_path))
    sim._lines.decide_green(Upcoming(libsumo, 0.0))
    gone_at, seen_at, moved_at, lines, stood = None, None, None, {}, False
    try:
        while sim.time_s() < 25.0:
            head = "c0"
            if head in sim.vehicle_ids():
                line = lines[sim.time_s()] = sim.stop_lines_m([head])[0]
                state = libsumo.trafficlight.getRedYellowGreenState("tl")
                if gone_at is None and sim.time_s() > 5.0 and line == np.inf:
                    gone_at = sim.time_s()
                if seen_at is None and state == "G":
                    seen_at = sim.time_s()
            sim.step()
            speed = libsumo.vehicle.getSpeed("c0")
            stood = stood or speed < 0.01
            if moved_at is None and stood and speed > 0.1:
                moved_at = sim.time_s()
    finally:
        sim.close()
    assert lines[19.5] < 2.0, lines[19.5]  # standing at its line a step before
    assert gone_at == 20.0, gone_at  # the last step that reads red
    assert seen_at == 20.0 + DT, seen_at  # the light shows green a step later
    assert moved_at == 20.0 + DT, moved_at  # SUMO's head moved in the switch step

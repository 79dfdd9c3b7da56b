"""``Simulation.decide_yellow(ahead=True)`` (``deploy.yellow = "ahead"``): a green link that turns yellow in the coming step is
decided now, from the state SUMO's own drivers decide it from (the light switches at the
start of SUMO's step, before they move); a driver that waited to see the yellow decided a
step late, a step nearer the line (arterial 1164: 29 cars that could brake crossed on the
yellow, the truth's none). Scripted answers, then a real SUMO light."""

from __future__ import annotations

from pathlib import Path

import libsumo
import numpy as np
from test_yellow_onset import DT, Scripted, light_cars, stop_lines_on_a

from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.stop_lines import StopLineReader, euler_brake_gap


def _reader(s: Scripted, upcoming: dict[str, str | None]) -> StopLineReader:
    reader = s.reader()
    reader.decide_yellow(lambda vid: s.v, lambda vid: 4.5, DT, upcoming.get)
    return reader


def test_a_yellow_in_the_coming_step_is_decided_now() -> None:
    """Green now, j1 yellow from the coming step: 30 m at 14 m/s (18.4 m to brake) is a
    stop now and stays one; 8 m passes, now and through the yellow; j2 does not switch."""
    s = Scripted()
    up: dict[str, str | None] = {"j1": "y", "j2": None}
    r = _reader(s, up)
    s.d = 30.0
    assert r.stop_line("car")[0] == 30.0  # decided on the last green step
    s.state, s.d = "y", 23.0
    assert r.stop_line("car")[0] == 23.0
    s2 = Scripted()
    r2 = _reader(s2, up)
    s2.d = 8.0
    assert r2.stop_line("car")[0] == np.inf  # it passes j1; j2 green: nothing ahead
    s2.state, s2.d = "y", 1.0
    assert r2.stop_line("car")[0] == 201.0  # j1 passed; j2 (yellow now) 201 m ahead


def test_the_upcoming_state_at_a_real_light(tmp_path: Path) -> None:
    """A (200 m) -> a light, green 30 s, yellow 4 s, red: ``Upcoming`` says the
    yellow only on the green's last step, and the light shows it after that step; every
    car decided then as the reader's rule (its Euler braking distance at 4.5 m/s^2 against
    its distance less 1 m) keeps its decision through the yellow."""
    sim = Simulation(light_cars(tmp_path))
    sim.decide_yellow(ahead=True)
    said, decided = [], {}
    try:
        while sim.time_s() < 36.0:
            sim.step()
            on_a, got = stop_lines_on_a(sim)
            up = sim._lines._upcoming("tl")
            state = libsumo.trafficlight.getRedYellowGreenState("tl")
            if up is not None:
                said.append((sim.time_s(), state, up))
            if state == "G" and up == "y":
                for v, (pos, speed) in on_a.items():
                    can = euler_brake_gap(speed, 4.5, DT) <= 200.0 - pos - 1.0
                    assert (got[v] < np.inf) == can, (v, pos, speed, got[v])
                    decided[v] = can
            elif state == "y":
                for v in set(decided) & set(got):
                    assert (got[v] < np.inf) == decided[v], (sim.time_s(), v)
    finally:
        sim.close()
    assert said[0][:3] == (29.5, "G", "y"), said
    assert decided and not all(decided.values()) and any(decided.values()), decided

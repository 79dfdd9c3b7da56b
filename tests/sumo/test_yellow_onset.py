"""``StopLineReader.decide_yellow``: a yellow decided once per vehicle and link at its onset
(SUMO's ``canBrakeBeforeStopLine``): a stop where the vehicle can brake before the line at
its decel, else it passes while the light stays yellow; never a red. Without it a yellow is a
stop (the default). Scripted answers (the reader's inputs are libsumo's), then a real SUMO
light."""

from __future__ import annotations

from pathlib import Path

import libsumo
import numpy as np
import pytest
from conftest import light_queue

from macromicro_sumo.road.physics import brake_gap
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.stop_lines import StopLineReader, euler_brake_gap

DT = 0.5


class Scripted:
    """One vehicle's getNextTLS answers and speed, set per step by the test."""

    def __init__(self) -> None:
        self.state, self.d, self.v = "G", 100.0, 14.0

    def next_tls(self, vid: str) -> list[tuple[str, int, float, str]]:
        return [("j1", 0, self.d, self.state), ("j2", 0, self.d + 200.0, self.state)]

    def reader(self) -> StopLineReader:
        """A reader of these answers: one lane m0_0 through one light link, no decision
        yet (each test decides the yellow or the green its own way)."""
        return StopLineReader(
            self.next_tls,
            lambda vid: "m0_0",
            lambda vid: [],
            lambda tls: [[("m0_0", "m1_0", ":j_0")]],
            lambda vid: "passenger",
            lambda vid: None,
            {},
        )


def _reader(s: Scripted, decide: bool) -> StopLineReader:
    reader = s.reader()
    if decide:
        reader.decide_yellow(lambda vid: s.v, lambda vid: 4.5, DT)
    return reader


def test_euler_brake_gap_is_road_physics() -> None:
    rng = np.random.default_rng(4)
    for v, b in zip(rng.uniform(0, 40, 500), rng.uniform(0.5, 9, 500), strict=True):
        assert euler_brake_gap(v, b, DT) == pytest.approx(float(brake_gap(v, b, DT)), abs=1e-12)


def test_a_yellow_is_a_stop_by_default() -> None:
    s = Scripted()
    s.state, s.d = "y", 5.0
    assert _reader(s, False).stop_line("car")[0] == 5.0


def test_one_that_cannot_brake_passes_the_yellow_not_the_red() -> None:
    """14 m/s, 8 m from the line at the onset (it needs 18.4 m at 4.5 m/s^2): it passes
    the yellow (the next line, yellow too but 208 m ahead, is its stop), and keeps passing
    while the light stays yellow, whatever its speed; a red is its stop again."""
    s = Scripted()
    r = _reader(s, True)
    assert r.stop_line("car")[0] == np.inf  # green: nothing ahead
    s.state, s.d = "y", 8.0
    assert r.stop_line("car")[0] == 208.0
    s.d, s.v = 2.0, 1.0  # it could stop now: decided at the onset, it still passes
    assert r.stop_line("car")[0] == 202.0
    s.state = "r"
    assert r.stop_line("car")[0] == 2.0


def test_one_that_can_brake_stops_for_the_whole_yellow() -> None:
    """30 m before the line at 14 m/s (18.4 m to brake): a stop; once decided it stays a
    stop when it came within its braking distance (a policy that kept its speed): that one
    brakes hard, as the truth's drivers never need to."""
    s = Scripted()
    r = _reader(s, True)
    s.state, s.d = "y", 30.0
    assert r.stop_line("car")[0] == 30.0
    s.d = 10.0
    assert r.stop_line("car")[0] == 10.0


def test_each_yellow_is_decided_afresh() -> None:
    """A decision holds for its yellow: after a red and a green the next yellow, met
    far enough to brake, is a stop; a vehicle forgotten has no decisions held."""
    s = Scripted()
    r = _reader(s, True)
    s.state, s.d = "y", 8.0
    assert r.stop_line("car")[0] == 208.0
    for state in ("r", "G"):
        s.state = state
        r.stop_line("car")
    s.state, s.d = "y", 60.0
    assert r.stop_line("car")[0] == 60.0
    r.forget(["car"])
    assert "car" not in r.passing


def light_cars(folder: Path) -> SumoOptions:
    """A (200 m, 13.9 m/s) -> a light, green 30 s, yellow 4 s, red -> B; 30 Krauss cars
    without dawdling, one every 1.5 s (also test_yellow_ahead's)."""
    vtype = 'sigma="0" decel="4.5" speedDev="0" minGap="2.5"'
    return light_queue(folder, 30, 1.5, ((30, "G"), (4, "y"), (100, "r")), vtype, DT)


def stop_lines_on_a(sim: Simulation) -> tuple[dict, dict]:
    """Each car on A's lane: (position, speed), and its stop line as the run's reader says."""
    veh = libsumo.vehicle
    on_a = {
        v: (veh.getLanePosition(v), veh.getSpeed(v))
        for v in sim.vehicle_ids()
        if veh.getLaneID(v) == "A_0"
    }
    ids = sorted(on_a)
    return on_a, dict(zip(ids, sim.stop_lines_m(ids).tolist(), strict=True))


def test_at_a_real_light_those_that_cannot_brake_pass_the_yellow(tmp_path: Path) -> None:
    """A (200 m, 13.9 m/s) -> a light, green 30 s, yellow 4 s, red -> B; Krauss cars
    without dawdling every 1.5 s. Every car on A asks its stop line every step: at the
    yellow's first step one whose Euler braking distance at 4.5 m/s^2 exceeds its distance
    less 1 m has none ahead (inf), the others the line; through the yellow the answers
    hold; at the red every car before the line has it."""
    sim = Simulation(light_cars(tmp_path))
    # The run's reader, told as a Simulation.decide_yellow would tell it (libsumo's answers).
    sim._lines.decide_yellow(libsumo.vehicle.getSpeed, libsumo.vehicle.getDecel, DT)
    first: dict[str, float] = {}
    passing: set[str] = set()
    try:
        while sim.time_s() < 40.0:
            sim.step()
            on_a, got = stop_lines_on_a(sim)
            state = libsumo.trafficlight.getRedYellowGreenState("tl")
            t = sim.time_s()
            if state == "y" and not first and on_a:  # the yellow's first step
                for v, (pos, speed) in on_a.items():
                    can = euler_brake_gap(speed, 4.5, DT) <= 200.0 - pos - 1.0
                    first[v] = got[v]
                    assert (got[v] < np.inf) == can, (v, pos, speed, got[v])
                    if not can:
                        passing.add(v)
            elif state == "y":
                for v in passing & set(got):
                    assert got[v] == np.inf, (t, v)
            elif state == "r":
                assert all(d < np.inf for d in got.values()), (t, got)
    finally:
        sim.close()
    assert first and passing and len(passing) < len(first), (first, passing)

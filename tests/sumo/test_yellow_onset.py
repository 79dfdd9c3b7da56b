"""``StopLineReader.decide_yellow``: a yellow decided once per vehicle and link at its onset
(SUMO's ``canBrakeBeforeStopLine``): a stop where the vehicle can brake before the line at
its decel, else it passes while the light stays yellow; never a red. Without it a yellow is a
stop (the default). Plain Python over scripted answers: the reader's inputs are libsumo's."""

from __future__ import annotations

import numpy as np
import pytest

from macromicro_sumo.road.physics import brake_gap
from macromicro_sumo.sumo.stop_lines import StopLineReader, euler_brake_gap

DT = 0.5


class Scripted:
    """One vehicle's getNextTLS answers and speed, set per step by the test."""

    def __init__(self) -> None:
        self.state, self.d, self.v = "G", 100.0, 14.0

    def next_tls(self, vid: str) -> list[tuple[str, int, float, str]]:
        return [("j1", 0, self.d, self.state), ("j2", 0, self.d + 200.0, self.state)]


def _reader(s: Scripted, decide: bool) -> StopLineReader:
    reader = StopLineReader(
        s.next_tls,
        lambda vid: "m0_0",
        lambda vid: [],
        lambda tls: [[("m0_0", "m1_0", ":j_0")]],
        lambda vid: "passenger",
        lambda vid: None,
        {},
    )
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

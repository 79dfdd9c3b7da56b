"""``deploy.yellow = "sumo"`` (``sumo.stop_lines.yellow_rule``): each car decides a yellow as
SUMO's own drivers (``MSVehicle::planMoveInternal``): from its state at the start of the step
in which the light switches, a stop where its distance less the lane's stopOffset holds its
Euler braking distance at max(min(3, emergencyDecel), decel). On a real light cycling
under SUMO's own cars, the reader's decision is each car's: a stop for those that stopped,
none for those that crossed on the yellow; "ahead" (a step earlier) and "onset" (a step
later, less 1 m) each get some cars wrong there (arterial 1161, stop 48)."""

from __future__ import annotations

from pathlib import Path

import libsumo
import pytest
from conftest import light_queue

from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.stop_lines import euler_brake_gap, sumo_stop_decel

DT = 0.5
LINE_M = 200.0


def _cycling_light(folder: Path, decel: float) -> SumoOptions:
    """A (200 m, 13.9 m/s) -> a light cycling green 10 s, yellow 4 s, red 6 s -> B; 120
    Krauss cars without dawdling, one every 1.7 s (its phase against the cycle moves, so the
    cars meet the yellow at every distance)."""
    vtype = f'sigma="0" decel="{decel:g}" speedDev="0" minGap="2.5"'
    phases = ((10, "G"), (4, "y"), (6, "r"))
    return light_queue(folder, 120, 1.7, phases, vtype, DT, LINE_M)


def _decisions(
    folder: Path, decel: float
) -> tuple[list[tuple[bool, bool, bool, bool]], list[tuple[float, float]]]:
    """Per car moving on A at a yellow onset: (reader's stop, SUMO's stop (it did not cross
    before the red), "ahead"'s stop, "onset"'s stop); and per car that stopped at the line
    (the first of its queue): (where the reader has it stop then, where it stood) [m before
    the line]."""
    sim = Simulation(_cycling_light(folder, decel))
    sim.decide_yellow(sumo=True)  # deploy.yellow = "sumo"
    veh, tl = libsumo.vehicle, libsumo.trafficlight
    out, pending, before, seen_y, stop_at, stood = [], {}, {}, {}, {}, []
    try:
        while sim.time_s() < 230.0:
            sim.step()
            state, now = tl.getRedYellowGreenState("tl"), sim.time_s()
            on_a = {
                v: (veh.getLanePosition(v), veh.getSpeed(v))
                for v in sim.vehicle_ids()
                if veh.getLaneID(v) == "A_0"
            }
            ids = sorted(on_a)
            got = dict(zip(ids, sim.stop_lines_m(ids).tolist(), strict=True))
            if state == "G" and tl.getNextSwitch("tl") <= now + 1e-9:
                assert sim._lines._upcoming("tl") == "y"
                b = decel
                for v, (pos, speed) in on_a.items():
                    if speed > 0.1:
                        prev = before.get(v, (pos, speed))
                        ahead = euler_brake_gap(prev[1], b, DT) <= LINE_M - prev[0] - 1.0
                        pending[v] = [got[v] < float("inf"), None, ahead, None]
                        # The driver stops its jmStoplineGap (1 m) before what it is told.
                        stop_at[v] = LINE_M - pos - (got[v] - 1.0)
            elif state == "y":
                for v in pending:
                    if v in on_a and v not in seen_y:
                        pos, speed = on_a[v]
                        seen_y[v] = euler_brake_gap(speed, b, DT) <= LINE_M - pos - 1.0
            elif state == "r" and pending:
                for v, row in pending.items():
                    row[1] = v in on_a  # still before the line at the red: it stopped
                    row[3] = seen_y.get(v, False)  # crossed before the yellow's first step
                    out.append(tuple(row))
                pending, seen_y = {}, {}
            for v, (pos, speed) in on_a.items():
                if v in stop_at and speed < 0.01 and LINE_M - pos < 1.5:
                    stood.append((stop_at.pop(v), LINE_M - pos))
            before = on_a
    finally:
        sim.close()
    return out, stood


@pytest.mark.parametrize("decel", [4.5, 2.0])
def test_each_car_decides_the_yellow_as_sumo_did(tmp_path: Path, decel: float) -> None:
    """At every yellow onset of a light cycling under SUMO's cars (decel 4.5; 2.0, where
    SUMO brakes at 3 m/s^2 for the yellow), the reader says a stop for exactly the cars
    that stopped; "ahead" and "onset" say otherwise for some."""
    rows = _decisions(tmp_path, decel)[0]
    assert len(rows) > 40, len(rows)
    assert [r[0] for r in rows] == [r[1] for r in rows], rows
    assert any(r[1] for r in rows) and not all(r[1] for r in rows)
    assert sum(r[2] != r[1] for r in rows) > 0  # "ahead": a step early
    assert sum(r[3] != r[1] for r in rows) > 0  # "onset": a step late


def test_a_car_that_decides_late_stops_nearer_the_line_as_sumos(tmp_path: Path) -> None:
    """A car whose braking distance leaves less than its jmStoplineGap (1 m) before the
    line stops nearer it (SUMO's laneStopOffset): the reader's stop, told at the switch,
    is where each of SUMO's cars stood, within 1 cm, some of them under 0.9 m."""
    stood = _decisions(tmp_path, 4.5)[1]
    assert len(stood) >= 5, stood
    assert all(abs(told - at) < 0.01 for told, at in stood), stood
    assert any(at < 0.9 for _, at in stood), stood


def test_the_stop_decel_is_raised_to_sumos_yellow_minimum() -> None:
    """max(min(3, emergencyDecel), decel): a low decel is raised to 3 m/s^2, not beyond
    its emergencyDecel; a decel above 3 stays."""
    decel = {"slow": 2.0, "weak": 1.5, "car": 4.5}
    emergency = {"slow": 9.0, "weak": 2.5, "car": 9.0}
    stop = sumo_stop_decel(decel.__getitem__, emergency.__getitem__)
    assert (stop("slow"), stop("weak"), stop("car")) == (3.0, 2.5, 4.5)


@pytest.mark.parametrize(("word", "ok"), [("sumo", True), ("sumo1", False)])
def test_the_setting_takes_sumo(tmp_path: Path, word: str, ok: bool) -> None:
    """``deploy.yellow = "sumo"`` loads (the driver hands it to ``Simulation.decide_yellow``);
    a word it does not know is refused, naming the field."""
    root = Path(__file__).resolve().parents[2] / "scenarios"
    text = (root / "highway_bremen.toml").read_text()
    text = text.replace("[deploy]\n", f'[deploy]\nyellow = "{word}"\n', 1)
    text = text.replace('"../sumo_nets', f'"{root.parent}/sumo_nets')
    path = tmp_path / "s.toml"
    path.write_text(text)
    if ok:
        assert load_scenario(path).deploy.yellow == "sumo"
    else:
        with pytest.raises(Exception, match="yellow"):
            load_scenario(path)

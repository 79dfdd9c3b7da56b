"""``deploy.green = "switch"``: a driven car's red line that turns green at the start of the
coming step is no stop in that step (``sumo.stop_lines.StopLineReader.decide_green``), as
SUMO's own drivers move off in the step the light switches in. With ``"seen"`` (the light
as it shows before the step) the head of every queue stood a step longer at each green
(drawn 1706, 4 runs: the truth's head at 1.1 m/s at the first green sample, the policy's at
0.2). A queue at a real SUMO light, driven at full throttle, against the same queue SUMO
drives itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from deploy_nets import queue_at_light

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run

GREEN_S = 80.0  # the light turns green [s]
DT = 0.5
LINE_M = 150.0  # the stop line: the end of A (deploy_nets.queue_at_light)


def _discharge(folder: Path, green: str | None) -> tuple[pd.DataFrame, dict]:
    """The queue's run: driven toward the limit at up to the accel bound with ``deploy.green
    = green``, or (None) driven by SUMO's own Krauss drivers (their vType's sigma 0.5)."""
    deploy = {} if green is None else {"green": green}
    sc = load_scenario(queue_at_light(folder / "q.toml", GREEN_S, deploy, b_m=300.0))
    net = sc.resolve(sc.network.net_file)
    section = read_section(net, ["A", "B"], False)
    driver = None
    if green is not None:
        a_max = sc.bounds.accel_mps2[1]

        def act(obs: np.ndarray) -> np.ndarray:
            return np.clip((obs[:, 1] - obs[:, 0]) / DT, -4.5, a_max)

        driver = SectionSpeedDriver(sc, section, 0, act, "sumo")
    routes = tuple(sc.resolve(r) for r in sc.network.route_files)
    options = SumoOptions(
        net, (net.parent / "light.add.xml",), DT, sc.seed, route_files=routes, user_demand=True
    )
    sim = Simulation(options)
    try:
        return record_run(sim, sc, section, 0, driver)
    finally:
        sim.close()


def _queue(df: pd.DataFrame) -> list[str]:
    """The cars standing at the green, the head first."""
    snap = df[(df["time_s"] == GREEN_S) & (df["speed_mps"] < 0.1)]
    return snap.sort_values("arc_m", ascending=False)["vehicle_id"].tolist()


def _first_move(df: pd.DataFrame, vid: str) -> float:
    """A car's first sample after the green above 0.5 m/s [s after the green]."""
    car = df[(df["vehicle_id"] == vid) & (df["time_s"] > GREEN_S)]
    return float(car.loc[car["speed_mps"] > 0.5, "time_s"].min()) - GREEN_S


def _crossing(df: pd.DataFrame, vid: str, arc_m: float) -> float:
    """When a car passes ``arc_m`` [s after the green], linear between its samples."""
    car = df[df["vehicle_id"] == vid].sort_values("time_s")
    return float(np.interp(arc_m, car["arc_m"], car["time_s"])) - GREEN_S


def test_the_head_moves_off_in_the_switch_step_as_sumos_drivers(tmp_path: Path) -> None:
    """SUMO's own head moves in the first step under the green (its first sample above 0.5
    m/s one step after the switch); driven with "switch" it does too, with "seen" a step
    later. The whole queue follows: every one of the first 8 cars crosses the line and 100 m
    past it earlier with "switch" than with "seen", the head by a step; none collides."""
    runs = {}
    for name in ("sumo", "seen", "switch"):
        runs[name], stats = _discharge(tmp_path / name, None if name == "sumo" else name)
        assert stats["collisions"] == 0 and stats["teleports"] == 0, (name, stats)
    queue = {name: _queue(df) for name, df in runs.items()}
    assert len(queue["seen"]) >= 10 and queue["seen"] == queue["switch"], queue
    head = {name: _first_move(df, queue[name][0]) for name, df in runs.items()}
    assert head["sumo"] == DT and head["switch"] == DT, head
    assert head["seen"] == 2 * DT, head
    seen, switch = runs["seen"], runs["switch"]
    for at in (LINE_M, LINE_M + 100.0):
        early = [_crossing(seen, v, at) - _crossing(switch, v, at) for v in queue["seen"][:8]]
        assert min(early) > 0.1, (at, early)
        assert abs(early[0] - DT) < 0.05, (at, early)


def test_seen_is_the_default_and_left_out_of_the_digest(tmp_path: Path) -> None:
    """Not moved without a measurement: "seen" is the default, and a scenario that leaves
    it there keeps its digest (omit_default); "switch" is in the scenario's table."""
    base = load_scenario(queue_at_light(tmp_path / "a" / "q.toml", GREEN_S, {}))
    assert base.deploy.green == "seen"
    assert "green" not in base.to_dict()["deploy"]
    on = load_scenario(queue_at_light(tmp_path / "b" / "q.toml", GREEN_S, {"green": "switch"}))
    assert on.to_dict()["deploy"]["green"] == "switch"

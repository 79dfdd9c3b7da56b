"""scripts/yellow_lanes.py: at a yellow onset, who could stop by SUMO's rule and what each
did (crossed, left the section, stopped), per lane, and the queue at the next green."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("yellow_lanes", ROOT / "scripts" / "yellow_lanes.py")
yl = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(yl)

LINE = 100.0


def _signals() -> pd.DataFrame:
    """One light at 100 m: green to 250 s, yellow 250-253 s, red to 260 s, green after."""
    rows = []
    for k in range(2400, 2700, 5):
        t = k / 10
        st = "G" if t < 250 else "y" if t < 253 else "r" if t < 260 else "G"
        rows.append((0, t, "j", 0, 0, 0.0, 0, LINE, st))
    cols = ["run", "time_s", "signal_id", "program", "phase", "left_s", "lane_index", "arc_m"]
    return pd.DataFrame(rows, columns=[*cols, "state"])


def _trajectories() -> pd.DataFrame:
    """At 249.5 s, 10 m/s: a 5 m from the line (cannot stop at 4.5: 8.75 m) crosses; b
    40 m away (can) stops 1 m before it and stands; c 3 m away (cannot) turns off the
    section (its samples end at 249.5 s); d, lane 1, 4 m away (cannot), stands before it."""
    rows = []
    for k in range(2400, 2700, 5):
        t = k / 10
        dt = t - 249.5
        a = LINE - 5 + 10 * dt
        b = min(LINE - 40 + 10 * dt, LINE - 1) if dt < 3.9 else LINE - 1
        vb = 0.0 if b >= LINE - 1 and dt > 0 else 10.0
        rows += [
            (0, t, "a", "car", False, 0, 0, a, 10.0, 0.0),
            (0, t, "b", "car", False, 0, 0, b, vb, 0.0),
        ]
        if t <= 249.5:
            rows.append((0, t, "c", "car", False, 0, 0, LINE - 3 + 10 * dt, 10.0, 0.0))
        rows.append((0, t, "d", "car", False, 1, 0, LINE - 4, 10.0 if dt <= 0 else 0.0, 0.0))
    cols = ["run", "time_s", "vehicle_id", "vtype", "observed", "lane_index", "edge_index"]
    return pd.DataFrame(rows, columns=[*cols, "arc_m", "speed_mps", "accel_mps2"])


def test_outcomes_and_queues_per_lane() -> None:
    ph = yl.phases(_signals(), LINE)
    assert ph[["yellow_s", "red_s", "green_s"]].values.tolist() == [[250.0, 253.0, 260.0]]
    cars, queues = yl.onset_cars(_trajectories(), LINE, ph, {"car": 4.5})
    got = cars.set_index("vehicle_id")
    assert got["can_stop"].to_dict() == {"a": False, "b": True, "c": False, "d": False}
    assert got["outcome"].to_dict() == {"a": "crossed", "b": "stopped", "c": "left", "d": "stopped"}
    s = yl.summary(cars, queues)
    assert s.loc[0, "could_not_crossed"] == 1 and s.loc[0, "could_not_left"] == 1
    assert s.loc[1, "could_not_stopped"] == 1 and s.loc[0, "could_stop_crossed"] == 0
    assert s.loc[0, "queue"] == 1 and s.loc[0, "queue_back_m"] == 1.0


def test_a_missing_file_is_one_line(tmp_path: Path, capsys) -> None:
    assert yl.main(["--signals", str(tmp_path / "no.csv"), "--arc", "1", "x=y.csv"]) == 2
    assert "no file" in capsys.readouterr().err

"""scripts/turner_lanes.py counts turners off their turn lane before a signal and the
greens a lane stalls in; bad input is one line. On trajectories.csv and signals.csv files
written as the deployment and the ground truth write them."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("turner_lanes", ROOT / "scripts" / "turner_lanes.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)

LINE = 500.0


def _signals(path: Path) -> Path:
    """One run, lanes 0 and 1 of j: red 0-10 s, green 10-50 s, red from 50 s."""
    rows = [
        {"run": 0, "time_s": t, "signal_id": "j", "lane_index": lane,
         "state": "G" if 10.0 <= t < 50.0 else "r"}
        for t in range(0, 60) for lane in (0, 1)
    ]  # fmt: skip
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def _trajectories(path: Path, stuck: bool) -> Path:
    """Lane 0 and lane 1 each pass a car every 2 s of green (10 m/s, at the line at
    t = 11, 13, ...); with ``stuck`` a turner t.0 stands on lane 1 at the line until 30 s
    and the lane-1 cars behind it pass only after it leaves (to lane 0)."""
    rows = []
    for lane in (0, 1):
        for k in range(15):
            t_line = 11.0 + 2.0 * k + (20.0 if stuck and lane == 1 else 0.0)
            if t_line >= 50.0:
                continue
            for t in range(0, 60):
                arc = LINE + 10.0 * (t - t_line)
                if LINE - 250.0 <= arc <= LINE + 50.0:
                    rows.append({"run": 0, "time_s": float(t), "vehicle_id": f"m{lane}.{k}",
                                 "lane_index": lane, "arc_m": arc, "speed_mps": 10.0})  # fmt: skip
    if stuck:
        for t in range(0, 31):
            rows.append({"run": 0, "time_s": float(t), "vehicle_id": "t.0", "lane_index": 1,
                         "arc_m": LINE - 2.0, "speed_mps": 0.0})  # fmt: skip
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def test_a_turner_standing_off_its_lane_stalls_the_green(tmp_path: Path, capsys) -> None:
    sig = script.greens(pd.read_csv(_signals(tmp_path / "s.csv")), "j", 0.0, 100.0)
    assert list(sig["g0"]) == [10.0, 10.0] and list(sig["r0"]) == [50.0, 50.0]
    free = pd.read_csv(_trajectories(tmp_path / "free.csv", stuck=False))
    stuck = pd.read_csv(_trajectories(tmp_path / "stuck.csv", stuck=True))
    g_free = script.per_green(script.crossings(free, LINE), sig).set_index("lane")
    g_stuck = script.per_green(script.crossings(stuck, LINE), sig).set_index("lane")
    assert g_free.loc[1, "n"] == 15 and not g_free["stalled"].any()
    assert g_stuck.loc[1, "n"] == 10 and g_stuck.loc[1, "first_s"] == pytest.approx(21.0)
    assert bool(g_stuck.loc[1, "stalled"]) and not bool(g_stuck.loc[0, "stalled"])
    t = script.turners(stuck, "t", LINE, 0)
    assert t["standing off lane: vehicles"] == 1.0 and t["standing off lane: veh-s"] == 31.0
    assert t["off lane 30-0 m %"] == 100.0
    argv = [f"a={tmp_path / 'free.csv'}", f"b={tmp_path / 'stuck.csv'}", "--line", "500",
            "--signal-id", "j", "--route", "t", "--signals", str(tmp_path / "s.csv")]  # fmt: skip
    assert script.main(argv) == 0
    assert "stalled" in capsys.readouterr().out
    assert script.main([*argv[:-2], "--signals", str(tmp_path / "s.csv"), "--to", "0"]) == 2
    assert script.main([*argv[:4], "--signal-id", "x", *argv[6:]]) == 2
    assert "no green of 'x'" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="nope.csv not found"):
        script.main([f"a={tmp_path / 'nope.csv'}", *argv[2:]])

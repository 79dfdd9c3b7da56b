"""scripts/station_headways.py: each vehicle's passage of a point from a trajectories.csv
(linear between its samples), the headway to the one before it in its run, by the
follower's vType; a missing file is a one-line error."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location(
    "station_headways", ROOT / "scripts" / "station_headways.py"
)
sh = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sh)


def trajectories(path: Path) -> Path:
    """Two runs; run 0: a car at 10 m/s passing 100 m at 10 s, an IDM car behind it 2.5 s
    later, a truck 4 s after that; run 1: one car (no headway)."""
    rows = []
    for run, vid, vtype, t_pass in ((0, "a", "car", 10.0), (0, "b", "car_idm", 12.5),
                                    (0, "c", "truck", 16.5), (1, "d", "car", 11.0)):  # fmt: skip
        for k in range(0, 41):
            t = k * 0.5
            rows.append((run, t, vid, vtype, 100.0 + 10.0 * (t - t_pass), 10.0))
    pd.DataFrame(rows, columns=sh.COLUMNS).to_csv(path, index=False)
    return path


def test_headways_by_the_followers_vtype(tmp_path: Path, capsys) -> None:
    traj = pd.read_csv(trajectories(tmp_path / "t.csv"))
    p = sh.passages(traj, 100.0)
    assert list(p["vehicle_id"]) == ["a", "b", "c", "d"]
    assert p["time_s"].tolist() == pytest.approx([10.0, 12.5, 16.5, 11.0])
    h = sh.headways(p, 0.0, 20.0)
    assert dict(zip(h["vehicle_id"], h["headway_s"], strict=True)) == pytest.approx(
        {"b": 2.5, "c": 4.0}
    )
    s = sh.summary(h, 2)
    assert s["passages_per_run"] == 1.0 and s["headway_s"] == pytest.approx(3.25)
    assert s["headway_truck_s"] == pytest.approx(4.0) and "headway_car_s" not in s
    assert sh.headways(p, 13.0, 20.0)["vehicle_id"].tolist() == ["c"]  # the window
    assert sh.main(["--arc", "100", f"x={tmp_path / 't.csv'}"]) == 0
    assert "3.25" in capsys.readouterr().out


def test_a_missing_file_is_one_line(tmp_path: Path, capsys) -> None:
    assert sh.main(["--arc", "100", f"x={tmp_path / 'none.csv'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.csv" in err[0]


def queue_files(tmp: Path) -> tuple[Path, Path]:
    """A stop line at 100 m, red until 10.0 s then green (signals.csv rows every 0.5 s, two
    links of the line: one row a step counts); three cars standing 7.5 m apart before it
    start 0.0, 1.0 and 2.5 s after the green; a fourth standing 300 m back (beyond
    REACH_M) and a fifth moving are not in the queue."""
    sig, traj = [], []
    for k in range(0, 81):
        t = k * 0.5
        for link in (0, 1):
            sig.append((0, t, "j1", 0, 0 if t < 10 else 2, 1.0, 0, 100.0 + 0.1 * link,
                        "r" if t < 10 else "G"))  # fmt: skip
        for vid, x0, start in (("a", 99.0, 10.0), ("b", 91.5, 11.0), ("c", 84.0, 13.5),
                               ("far", -200.0, 20.0), ("m", 50.0, -1.0)):  # fmt: skip
            moving = t >= start
            v = 0.0 if not moving else 2.0
            x = x0 + (2.0 * (t - start) if moving else 0.0)
            traj.append((0, t, vid, "car", x, v))
    s, p = tmp / "signals.csv", tmp / "traj.csv"
    pd.DataFrame(sig, columns=["run", "time_s", "signal_id", "program", "phase", "left_s",
                               "lane_index", "arc_m", "state"]).to_csv(s, index=False)  # fmt: skip
    pd.DataFrame(traj, columns=sh.COLUMNS).to_csv(p, index=False)
    return s, p


def test_start_lags_of_the_queue_at_green(tmp_path: Path, capsys) -> None:
    s, p = queue_files(tmp_path)
    onsets = sh.green_onsets(pd.read_csv(s), 100.0)
    assert onsets["time_s"].tolist() == [10.0]  # one onset, though two links carry it
    lags = sh.start_lags(pd.read_csv(p), 100.0, onsets)
    assert lags["vehicle_id"].tolist() == ["a", "b", "c"]  # queue order; far, m left out
    assert lags["start_s"].tolist() == pytest.approx([0.0, 1.0, 3.5])  # > MOVING_MPS
    assert lags["lag_s"].tolist() == pytest.approx([0.0, 1.0, 2.5])
    got = sh.lag_summary(lags)
    assert got["queues"] == 1 and got["lag_2-4"] == pytest.approx(1.75)
    assert sh.main(["--arc", "100", "--start-lags", str(s), f"x={p}"]) == 0
    assert "1.75" in capsys.readouterr().out


def test_start_lags_needs_its_signals_and_one_arc_for_headways(tmp_path: Path, capsys) -> None:
    _, p = queue_files(tmp_path)
    assert sh.main(["--arc", "100", "--start-lags", str(tmp_path / "none.csv"), f"x={p}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.csv" in err[0]
    assert sh.main(["--arc", "100", "--arc", "200", f"x={p}"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def yellow_files(tmp: Path) -> tuple[Path, Path]:
    """A stop line at 100 m: green until 10.0 s, yellow until 13.0 s, red after. At 9.5 s
    (the last sample before the yellow) "near" is 5 m before it at 10 m/s (it needs 8.75 m
    to brake at 4.5 m/s^2 in Euler steps of 0.5 s: it cannot) and drives on; "far" is
    50 m before it at 10 m/s (it can) and stops at 99 m; "truck", 9.5 m before it at 10
    m/s, could brake at --decel truck=9 (4.45 m) but not at 4.5, and crosses at 11 s."""
    sig, traj = [], []
    for k in range(0, 61):
        t = k * 0.5
        state = "G" if t < 10 else "y" if t < 13 else "r"
        sig.append((0, t, "j1", 0, 0, 1.0, 0, 100.0, state))
        traj.append((0, t, "near", "car", 95.0 + 10.0 * (t - 9.5), 10.0))
        x = min(50.0 + 10.0 * (t - 9.5), 99.0)
        traj.append((0, t, "far", "car", x, 10.0 if x < 99.0 else 0.0))
        traj.append((0, t, "truck", "truck", 90.5 + 10.0 * (t - 9.5), 10.0))
    s, p = tmp / "signals.csv", tmp / "traj.csv"
    pd.DataFrame(sig, columns=["run", "time_s", "signal_id", "program", "phase", "left_s",
                               "lane_index", "arc_m", "state"]).to_csv(s, index=False)  # fmt: skip
    pd.DataFrame(traj, columns=sh.COLUMNS).to_csv(p, index=False)
    return s, p


def test_who_could_brake_and_who_crossed_at_the_yellow(tmp_path: Path, capsys) -> None:
    s, p = yellow_files(tmp_path)
    onsets = sh.yellow_onsets(pd.read_csv(s), 100.0)
    assert onsets[["time_s", "red_s"]].values.tolist() == [[10.0, 13.0]]
    cars = sh.at_yellow(pd.read_csv(p), 100.0, onsets, {}).set_index("vehicle_id")
    assert cars["can_brake"].to_dict() == {"near": False, "far": True, "truck": False}
    assert cars["crossed"].to_dict() == {"near": True, "far": False, "truck": True}
    braked = sh.at_yellow(pd.read_csv(p), 100.0, onsets, {"truck": 9.0})
    assert braked.set_index("vehicle_id").loc["truck", "can_brake"]
    got = sh.yellow_summary(cars.reset_index())
    assert got == {"onsets": 1.0, "could_brake": 1.0, "could_brake_crossed": 0.0,
                   "could_not": 2.0, "could_not_crossed": 2.0}  # fmt: skip
    assert sh.main(["--arc", "100", "--yellow-onsets", str(s), f"x={p}"]) == 0
    assert "could_not_crossed" in capsys.readouterr().out
    # Onsets outside --from / --to are left out; a bad --decel is one line.
    assert sh.main(["--arc", "100", "--from", "20", "--yellow-onsets", str(s), f"x={p}"]) == 0
    assert capsys.readouterr().out.splitlines()[1].split()[:2] == ["x", "0.0"]
    assert sh.main(["--arc", "100", "--decel", "truck", "--yellow-onsets", str(s), f"x={p}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--decel truck" in err[0]


def green_files(tmp: Path) -> tuple[Path, Path]:
    """A stop line at 100 m: red until 10.0 s, green until 40.0, yellow until 43.0, red
    after. On lane 0, 13 cars cross at 11, 13, ..., 35 s (one every 2 s) and one more at
    44 s (after the red: not counted); on lane 1 one car crosses at 12 s; one car crosses
    lane 0 at 5 s (before the onset: not counted)."""
    sig, traj = [], []
    crossings = [(f"c{k}", 0, 11.0 + 2.0 * k) for k in range(13)]
    crossings += [("late", 0, 44.0), ("l1", 1, 12.0), ("early", 0, 5.0)]
    for k in range(0, 101):
        t = k * 0.5
        state = "r" if t < 10 else "G" if t < 40 else "y" if t < 43 else "r"
        sig.append((0, t, "j1", 0, 0, 1.0, 0, 100.0, state))
        for vid, lane, t_cross in crossings:
            traj.append((0, t, vid, "car", 100.0 + 10.0 * (t - t_cross), 10.0, lane))
    s, p = tmp / "signals.csv", tmp / "traj.csv"
    pd.DataFrame(sig, columns=["run", "time_s", "signal_id", "program", "phase", "left_s",
                               "lane_index", "arc_m", "state"]).to_csv(s, index=False)  # fmt: skip
    pd.DataFrame(traj, columns=[*sh.COLUMNS, "lane_index"]).to_csv(p, index=False)
    return s, p


def test_crossings_per_green_and_the_saturation_headway(tmp_path: Path, capsys) -> None:
    s, p = green_files(tmp_path)
    windows = sh.green_windows(pd.read_csv(s), 100.0)
    assert windows[["time_s", "red_s"]].values.tolist() == [[10.0, 43.0]]  # green + yellow
    d = sh.green_discharge(pd.read_csv(p), 100.0, windows).set_index("lane")
    assert d["crossings"].to_dict() == {0: 13, 1: 1}  # "late" and "early" left out
    assert d.loc[0, ["t_1_s", "t_4_s", "t_12_s"]].tolist() == pytest.approx([1.0, 7.0, 23.0])
    assert d.loc[0, "sat_headway_s"] == pytest.approx(2.0) and np.isnan(d.loc[1, "t_4_s"])
    got = sh.green_summary(d.reset_index())
    assert got["crossings"] == pytest.approx(7.0) and got["with_12"] == 1.0
    assert got["sat_headway_s"] == pytest.approx(2.0)
    # The start-up: t_1 and the 2nd-6th crossings' headways, of the lanes with 6 crossings.
    assert d.loc[0, [f"h_{k}_s" for k in sh.HEADWAYS]].tolist() == pytest.approx([2.0] * 5)
    assert np.isnan(d.loc[1, "h_2_s"])
    assert got["with_6"] == 1.0 and got["t_1_of6_s"] == pytest.approx(1.0)
    assert got["h_2_s"] == pytest.approx(2.0) and got["h_6_s"] == pytest.approx(2.0)
    assert sh.main(["--arc", "100", "--greens", str(s), f"x={p}"]) == 0
    assert "h_6_s" in capsys.readouterr().out
    assert sh.main(["--arc", "100", "--greens", str(s), "--start-lags", str(s), f"x={p}"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_pull_away_speeds_and_crossings_by_queue_position(tmp_path: Path, capsys) -> None:
    """The queue of ``queue_files`` (green at 10 s, line at 100 m; a, b, c at 2 m/s from 10,
    11 and 13.5 s): by position the speed 0 and 2 s after the green and when each passes the
    line and 50 m past it; 100 m past it is beyond the samples (NaN)."""
    s, p = queue_files(tmp_path)
    onsets = sh.green_onsets(pd.read_csv(s), 100.0)
    d = sh.pull_away(pd.read_csv(p), 100.0, onsets).set_index("position")
    assert d.index.tolist() == [1, 2, 3]
    assert d["v_0s"].tolist() == pytest.approx([2.0, 0.0, 0.0])
    assert d["v_2s"].tolist() == pytest.approx([2.0, 2.0, 0.0])
    assert d["x_0m"].tolist() == pytest.approx([0.5, 5.25, 11.5])  # 1, 8.5, 16 m at 2 m/s
    assert d.loc[1, "x_50m"] == pytest.approx(25.5) and d["x_100m"].isna().all()
    assert sh.main(["--arc", "100", "--pull-away", str(s), f"x={p}"]) == 0
    assert "x_50m" in capsys.readouterr().out
    assert sh.main(["--arc", "100", "--pull-away", str(s), "--greens", str(s), f"x={p}"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1

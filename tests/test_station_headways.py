"""scripts/station_headways.py: each vehicle's passage of a point from a trajectories.csv
(linear between its samples), the headway to the one before it in its run, by the
follower's vType; a missing file is a one-line error."""

from __future__ import annotations

import importlib.util
from pathlib import Path

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

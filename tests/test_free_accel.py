"""scripts/free_accel.py: the acceleration by speed of free rows (no leader within the gap on
the lane, now and next step) or of every accelerating row, from a trajectories.csv; bad
input is a one-line error."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("free_accel", ROOT / "scripts" / "free_accel.py")
fa = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fa)

DT_S = 0.5


def trajectories(path: Path) -> Path:
    """Run 0 on lane 0: car ``a`` starts at 0 m from standstill at 2.0 m/s^2 up to 12 m/s,
    alone ahead; truck ``b`` starts 20 m behind it and drives as it does (never free: a is
    20 m ahead). Lane 1: car ``c`` at 1.5 m/s^2 up to 9 m/s with a gap in its samples (5-6 s
    missing). Run 1: car ``d`` as ``a`` (another run, no leader)."""
    rows = []
    specs = (
        (0, "a", "car", 0, 0.0, 2.0, 12.0),
        (0, "b", "truck", 0, -20.0, 2.0, 12.0),
        (0, "c", "car", 1, 0.0, 1.5, 9.0),
        (1, "d", "car", 0, 0.0, 2.0, 12.0),
    )
    for run, vid, vtype, lane, x0, accel, top in specs:
        v, x = 0.0, x0
        for k in range(41):
            t = k * DT_S
            if not (vid == "c" and 5.0 <= t < 6.5):
                rows.append((run, t, vid, vtype, lane, x, v))
            x += v * DT_S
            v = min(v + accel * DT_S, top)
    pd.DataFrame(rows, columns=fa.COLUMNS).to_csv(path, index=False)
    return path


def test_free_rows_and_every_accelerating_row(tmp_path: Path) -> None:
    traj = pd.read_csv(trajectories(tmp_path / "t.csv"))
    t = fa.with_accel(traj)
    a = t[t["vehicle_id"] == "a"].set_index("time_s")
    assert a.loc[0.0, "gap_m"] != a.loc[0.0, "gap_m"]  # NaN: nobody ahead of a
    b = t[t["vehicle_id"] == "b"].set_index("time_s")
    assert b.loc[0.0, "gap_m"] == pytest.approx(20.0)
    assert a.loc[1.0, "accel_next"] == pytest.approx(2.0)
    c = t[t["vehicle_id"] == "c"].set_index("time_s")
    assert np.isnan(c.loc[4.5, "accel_next"])  # its next sample is 2 s later, not a step
    free = fa.selected(t, 40.0, 0.0)
    assert "b" not in set(free["vehicle_id"])  # a is 20 m ahead of it: never free
    assert set(free["vehicle_id"]) == {"a", "c", "d"}
    # a's speeds 1, 2, ..., 9 m/s (v = 0 is not moving) each gain 1 m/s a step: 2.0 m/s^2,
    # all above SUMO's default Krauss mean; 10 and 11 m/s too, 12 m/s cruises
    table = fa.by_speed(free[free["vehicle_id"] == "a"], (0.0, 10.0, 20.0), fa.CAP_MPS2)
    assert table["rows"].tolist() == [9, 2 + 28]  # 41 samples, the last without a next
    assert table.iloc[0]["accel_mps2"] == pytest.approx(2.0) and table.iloc[0]["above_cap"] == 1.0
    assert table.iloc[1]["accel_mps2"] == pytest.approx(2.0 * 2 / 30)
    cruise = free[(free["vehicle_id"] == "c") & (free["speed_mps"] == 9.0)]
    assert len(cruise) > 0 and (cruise["accel_next"] == 0.0).all()
    every = fa.selected(t, 40.0, 0.0, every=True, vtype="truck")
    assert set(every["vehicle_id"]) == {"b"} and len(every) == 11  # 1-11 m/s; 0 is standing
    assert every["accel_next"].to_numpy() == pytest.approx(2.0)
    zone = fa.selected(t, 40.0, 0.0, zone=(0.0, 10.0))
    assert zone["arc_m"].between(0.0, 10.0, inclusive="left").all() and len(zone) < len(free)
    above = fa.by_speed(free[free["vehicle_id"] == "c"], (0.0, 10.0), 1.95)["above_cap"]
    assert above.iloc[0] == 0.0  # 1.5 m/s^2 is below SUMO's default mean


def test_main_prints_a_table_and_bad_input_is_one_line(tmp_path: Path, capsys) -> None:
    path = trajectories(tmp_path / "t.csv")
    assert fa.main(["--from", "0", "--bins", "0,10,20", f"x={path}", f"y={path}"]) == 0
    out = capsys.readouterr().out
    assert "x_n" in out and "y>1.95" in out and "[10.0, 20.0)" in out
    assert fa.main([f"x={tmp_path / 'none.csv'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.csv" in err[0]
    assert fa.main(["--bins", "5,1", f"x={path}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--bins" in err[0]

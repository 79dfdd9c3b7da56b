"""scripts/junction_entry.py counts cars slow inside a junction and cars waiting at a green
line with no room past the junction; bad input is one line."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location(
    "junction_entry", ROOT / "scripts" / "junction_entry.py"
)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)

LINE = 100.0


def _files(tmp_path: Path) -> tuple[Path, Path]:
    """Two steps, the line green at the first only: a car standing 2 m before the line
    behind a car whose back is 3 m past the junction's 19 m (no room), a car creeping at
    1 m/s and one at 8 m/s inside the junction; at the second step (red) the same."""
    rows = []
    for t in (300.0, 300.5):
        rows += [
            (0, t, "w", "car", LINE - 2.0, 0.0),
            (0, t, "a", "car", LINE + 19.0 + 5.0 + 3.0, 0.0),
            (0, t, "s", "car", LINE + 5.0, 1.0),
            (0, t, "f", "car", LINE + 12.0, 8.0),
        ]
    traj = tmp_path / "trajectories.csv"
    pd.DataFrame(rows, columns=script.COLUMNS).to_csv(traj, index=False)
    sig = tmp_path / "signals.csv"
    pd.DataFrame(
        [(0, 300.0, "j1", 0, 0, 10.0, 0, LINE, "G"), (0, 300.5, "j1", 0, 1, 3.0, 0, LINE, "y")],
        columns=["run", "time_s", "signal_id", "program", "phase", "left_s", "lane_index",
                 "arc_m", "state"],
    ).to_csv(sig, index=False)  # fmt: skip
    return traj, sig


def test_counts(tmp_path: Path) -> None:
    traj, sig = _files(tmp_path)
    _, t = script.load(f"x={traj}", 240.0)
    green = script.green_at(pd.read_csv(sig), LINE)
    got = script.line_counts(script.with_ahead(t), LINE, 19.0, green)
    # in the junction: s and f at both steps; slow: s; waiting on green: w once, behind s
    assert got == {"in": 4, "slow": 2, "standing": 0, "wait": 1, "wait_no_room": 1}
    # the junction empty: the car ahead is "a", 3 m past it (no room), or 11 m (room)
    green = script.green_at(pd.read_csv(sig), LINE)
    t2 = t[t["vehicle_id"].isin(["w", "a"])].reset_index(drop=True)
    got = script.line_counts(script.with_ahead(t2), LINE, 19.0, green)
    assert got["in"] == 0 and got["wait"] == 1 and got["wait_no_room"] == 1
    t3 = t2.assign(arc_m=t2["arc_m"].where(t2["vehicle_id"] != "a", t2["arc_m"] + 8.0))
    got = script.line_counts(script.with_ahead(t3), LINE, 19.0, green)
    assert got["wait"] == 1 and got["wait_no_room"] == 0


def test_main_prints_a_row_per_file_and_line(tmp_path: Path, capsys) -> None:
    traj, sig = _files(tmp_path)
    script.main([f"truth={traj}", "--arc", str(LINE), "--signals", str(sig)])
    out = capsys.readouterr().out
    assert "truth" in out and "wait_no_room" in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["x=nope.csv"], "nope.csv: no such file"),
        (["x"], "expected LABEL=TRAJECTORIES_CSV"),
        (["--arc", "555"], "no signal at arc 555"),
        (["--junction", "0"], "--junction: 0.0 m, accepted (0.5, 100]"),
    ],
)
def test_bad_input_is_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    traj, sig = _files(tmp_path)
    base = [f"x={traj}", "--signals", str(sig)]
    argv = [a for a in base if not (args and args[0].startswith("x") and a.startswith("x="))]
    argv = [*argv, *args]
    if "--arc" not in argv:
        argv += ["--arc", str(LINE)]
    with pytest.raises(SystemExit, match=message.replace("(", r"\(").replace("[", r"\[")):
        script.main(argv)

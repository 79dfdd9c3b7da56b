"""scripts/platoon_leaders.py splits detector passages into platoon leaders (a headway over
--free-headway to the previous passage at the same detector) and followers, per source and time
bin, on the chosen detectors and runs; bad input is one line. On passages written as the ground
truth and scripts/deploy_runs.py write them (run, detector_id, time_s, vehicle_id, speed_mps)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location(
    "platoon_leaders", ROOT / "scripts" / "platoon_leaders.py"
)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def _passages(path: Path, leader_speed: float) -> Path:
    """Runs 0 and 1, detector i_auto_m1_0_500: platoons of four, their leader 10 s after the
    previous platoon's last car at ``leader_speed``, followers 1.5 s apart at 18 m/s; one
    passage on m0 at 5 m/s that the m1 filter must drop."""
    rows = []
    for run in (0, 1):
        t = 0.0
        for platoon in range(3):
            for k in range(4):
                t += 10.0 if k == 0 else 1.5
                v = leader_speed if k == 0 else 18.0
                rows.append((run, "i_auto_m1_0_500", t, f"v{platoon}.{k}", v, 5.0))
        rows.append((run, "i_auto_m0_0_15", 1.0, "x", 5.0, 5.0))
    cols = ["run", "detector_id", "time_s", "vehicle_id", "speed_mps", "length_m"]
    pd.DataFrame(rows, columns=cols).to_csv(path, index=False)
    return path


def test_leaders_are_the_passages_after_a_long_headway(tmp_path: Path) -> None:
    d = script.passages(_passages(tmp_path / "p.csv", 20.0), "_m1_", [1])
    assert set(d["run"]) == {1} and (d["detector_id"] == "i_auto_m1_0_500").all()
    t = script.leaders(d, 4.0, None).loc["all"]
    # per run the first passage has no headway: 2 leaders (platoons 2, 3) and 9 followers
    assert t.loc["leader", "n"] == 2 and t.loc["leader", "speed_mps"] == pytest.approx(20.0)
    assert t.loc["follower", "n"] == 9 and t.loc["follower", "headway_s"] == pytest.approx(1.5)
    assert t.loc["all", "n"] == 11
    # a longer free headway than the platoons' gap: nobody leads
    assert "leader" not in script.leaders(d, 11.0, None).loc["all"].index
    binned = script.leaders(d, 4.0, [0.0, 20.0, 100.0])
    assert binned.loc[("[0.0, 20.0)", "follower"), "n"] == 3


def test_main_prints_each_source_and_refuses_bad_input(tmp_path: Path, capsys) -> None:
    slow = _passages(tmp_path / "slow.csv", 16.0)
    fast = _passages(tmp_path / "fast.csv", 21.0)
    assert script.main([f"truth={fast}", f"policy={slow}", "--detectors", "_m1_"]) == 0
    out = capsys.readouterr().out
    assert "policy" in out and "truth" in out and "16.0" in out and "21.0" in out
    assert script.main([str(slow), "--detectors", "_m1_"]) == 2
    assert "LABEL=PATH" in capsys.readouterr().err
    assert script.main([f"a={slow}", "--detectors", "_m1_", "--bins", "5", "1"]) == 2
    assert "--bins" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="not found"):
        script.main([f"a={tmp_path / 'none.csv'}", "--detectors", "_m1_"])
    with pytest.raises(SystemExit, match="no passage at detectors"):
        script.main([f"a={slow}", "--detectors", "_m9_"])
    pd.DataFrame({"run": [0]}).to_csv(tmp_path / "bad.csv", index=False)
    with pytest.raises(SystemExit, match="no column detector_id"):
        script.main([f"a={tmp_path / 'bad.csv'}", "--detectors", "_m1_"])

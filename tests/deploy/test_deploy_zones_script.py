"""scripts/deploy_zones.py splits a deployment's speed error by zone around the stop lines
and by lane, with each lane's share of its station's flow; bad input is one line."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("deploy_zones", ROOT / "scripts" / "deploy_zones.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def test_zones_around_a_line() -> None:
    lines = np.array([300.0, 600.0])
    got = [script.zone_of(a, lines, 60.0, 900.0) for a in (15, 200, 290, 299.5, 320, 400, 950)]
    assert got == ["entry", "far before", "before", "at line", "past", "far past", "exit"]


def test_the_error_lies_where_the_rows_put_it(tmp_path: Path, capsys) -> None:
    """Stations at 200 m (far before the line at 300 m: 2 m/s slow on lane 1 alone, which
    carries a third of its flow against the truth's half) and 320 m (exact)."""
    rows = []
    for arc in (200.0, 320.0):
        for lane, q_truth, q_meth in ((-1, 1200, 1200), (0, 600, 800), (1, 600, 400)):
            off = -2.0 if arc == 200.0 and lane in (-1, 1) else 0.0
            rows.append({"method": "policy", "run": 0, "station": f"e1_{arc:.0f}m",
                         "lane": lane, "begin_s": 0.0, "arc_m": arc, "flow_truth_vph": q_truth,
                         "flow_method_vph": q_meth, "speed_truth_mps": 15.0,
                         "speed_method_mps": 15.0 + off})  # fmt: skip
    path = tmp_path / "deploy_comparison.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    _, c = script.load(f"policy={path}")
    c = c.assign(zone=[script.zone_of(a, np.array([300.0]), 60.0, 900.0) for a in c["arc_m"]])
    z = c[c["lane"] == -1].groupby("zone").apply(script.scores, include_groups=False)
    assert z.loc["far before", "bias"] == -2.0 and z.loc["past", "rmse"] == 0.0
    share = script.lane_shares(c)
    assert share.loc[1, "truth %"] == pytest.approx(50.0)
    assert share.loc[1, "method %"] == pytest.approx(100.0 / 3.0)
    assert script.main([f"policy={path}", "--lines", "300"]) == 0
    assert "far before" in capsys.readouterr().out
    assert script.main([f"policy={path}", "--lines", "300", "--entry", "900"]) == 2
    with pytest.raises(SystemExit, match="no rows of method 'oracle'"):
        script.main([f"oracle={path}", "--lines", "300"])
    with pytest.raises(SystemExit, match="expected LABEL=PATH"):
        script.main([str(path), "--lines", "300"])

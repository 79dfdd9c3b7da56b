"""scripts/deploy_split.py splits a deployment's station errors by position (before / after
a cut) and interval, and per run; bad input is one line. On comparison files written as
scripts/deploy_runs.py writes them (a station row per lane -1; a per-lane row ignored)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("deploy_split", ROOT / "scripts" / "deploy_split.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def _folder(path: Path, downstream_error: float) -> Path:
    """Two runs, stations at 100 m (exact) and 900 m (``downstream_error`` m/s too fast from
    120 s on, 60 veh/h too many), intervals at 0, 60, 120, 180 s; one per-lane row off by
    50 m/s that must not count."""
    rows = []
    for run in (0, 1):
        for arc in (100.0, 900.0):
            for t in (0.0, 60.0, 120.0, 180.0):
                off = downstream_error if arc > 500 and t >= 120 else 0.0
                rows.append(
                    {
                        "method": "policy", "run": run, "station": f"e1_{arc:.0f}m",
                        "lane": -1, "begin_s": t, "arc_m": arc, "flow_truth_vph": 1000.0,
                        "flow_method_vph": 1000.0 + (60.0 if off else 0.0),
                        "speed_truth_mps": 20.0, "speed_method_mps": 20.0 + off,
                    }
                )  # fmt: skip
    rows.append({**rows[0], "lane": 0, "speed_method_mps": 70.0})
    path.mkdir()
    pd.DataFrame(rows).to_csv(path / "deploy_comparison.csv", index=False)
    return path


def test_the_split_finds_where_and_when_a_deployment_errs(tmp_path: Path, capsys) -> None:
    rows = script.station_rows(_folder(tmp_path / "b", 2.0), "policy")
    assert (rows["lane"] == -1).all() and len(rows) == 16
    t = script.split(rows, 500.0, [0.0, 120.0, 240.0]).set_index(["where", "run", "when"])
    late, early = t.loc[("down", "all", "[120.0, 240.0)")], t.loc[("down", "all", "[0.0, 120.0)")]
    assert late["speed_rmse_mps"] == pytest.approx(2.0) and late["flow_bias_vph"] == 60.0
    assert early["speed_rmse_mps"] == 0.0
    assert t.loc[("up", 0, "all"), "speed_rmse_mps"] == 0.0
    # per run downstream: half its intervals 2 m/s off
    assert t.loc[("down", 1, "all"), "speed_rmse_mps"] == pytest.approx(np.sqrt(2.0))
    argv = [str(_folder(tmp_path / "a", 0.0)), str(tmp_path / "b"), "--cut", "500"]
    assert script.main([*argv, "--bins", "0", "120", "240"]) == 0
    assert "speed_rmse_mps" in capsys.readouterr().out
    assert script.main([*argv, "--bins", "120", "0"]) == 2
    assert "--bins" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="deploy_comparison.csv not found"):
        script.main([str(tmp_path), "--cut", "500"])


def test_the_decomposition_tells_a_level_from_a_wave_at_another_time() -> None:
    """Upstream a wave (20 -> 5 -> 20 m/s) the method has one interval late, downstream the
    truth's speeds 1 m/s slow: the upstream error is all timing (same level, same swing),
    the downstream one all level; each zone's parts sum to its MSE."""
    truth_up = [20.0, 5.0, 20.0, 20.0]
    late_up = [20.0, 20.0, 5.0, 20.0]
    rows = [
        {"arc_m": arc, "speed_truth_mps": t, "speed_method_mps": m}
        for arc, ts, ms in (
            (100.0, truth_up, late_up),
            (900.0, [20.0, 21.0, 22.0, 21.0], [19.0, 20.0, 21.0, 20.0]),
        )
        for t, m in zip(ts, ms, strict=True)
    ]
    d = script.decompose(pd.DataFrame(rows), 500.0)
    parts = d[["level", "swing", "timing"]].sum(axis=1)
    assert np.allclose(parts, d["speed_rmse_mps"] ** 2)
    assert d.loc["up", "level"] == 0.0 and d.loc["up", "swing"] == 0.0
    assert d.loc["up", "timing"] == pytest.approx(2 * 15.0**2 / 4)  # two intervals 15 off
    assert d.loc["down", "level"] == pytest.approx(1.0) and d.loc["down", "timing"] < 1e-12
    assert d.loc["down", "corr"] == pytest.approx(1.0)
    assert d.loc["all", "n"] == 8

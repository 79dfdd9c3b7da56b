"""scripts/fresh_table.py: the deploy-log table of a fresh net from deploy_runs.py outputs,
and the stations where one method loses to another."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("fresh_table", ROOT / "scripts" / "fresh_table.py")
ft = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ft)


def deploy_folder(folder: Path, method: str, speeds: dict[float, list[float]]) -> Path:
    """A deploy_runs.py output of ``method``: per station arc, the method's speed in each
    interval (truth 10 m/s everywhere), run 0 only, plus its pooled rows (lane -1)."""
    folder.mkdir(parents=True)
    rows = []
    for station, (arc, vs) in enumerate(speeds.items()):
        for i, v in enumerate(vs):
            for lane in (-1, 0):  # a lane row must not count as a station row
                rows.append(
                    {"method": method, "run": 0, "station": station, "lane": lane,
                     "begin_s": 60.0 * i, "end_s": 60.0 * (i + 1), "arc_m": arc,
                     "speed_truth_mps": 10.0, "speed_method_mps": v if lane < 0 else 99.0}
                )  # fmt: skip
    pd.DataFrame(rows).to_csv(folder / "deploy_comparison.csv", index=False)
    errs = [v - 10.0 for vs in speeds.values() for v in vs]
    rmse = float(pd.Series(errs).pow(2).mean() ** 0.5)
    summary = {
        "method": method, "speed_rmse_mps": rmse, "speed_bias_mps": float(pd.Series(errs).mean()),
        "density_rmse_vpkm": 1.0, "share_geh_below_5": 0.9, "share_speed_within_5pct": 0.5,
        "collisions": 0, "teleports": 0, "emergency_brakings": 3,
    }  # fmt: skip
    pd.DataFrame([summary]).to_csv(folder / "deploy_summary.csv", index=False)
    pd.DataFrame([{"method": method, "run": 0, "speed_rmse_mps": rmse}]).to_csv(
        folder / "deploy_runs.csv", index=False
    )
    return folder


def test_table_and_the_station_that_loses(tmp_path: Path, capsys) -> None:
    # the policy is better at 100 m and much worse at 900 m: 900 m must lead the gaps
    pol = deploy_folder(tmp_path / "p", "policy", {100.0: [10.0, 10.0], 900.0: [7.0, 13.0]})
    base = deploy_folder(tmp_path / "b", "sumo_default", {100.0: [11.0, 9.0], 900.0: [10.5, 9.5]})
    floor = tmp_path / "floor.csv"
    pd.DataFrame(
        [{"pair": "all", "share_geh_below_5": 0.8, "share_speed_within_5pct": 0.6,
          "speed_rmse_mps": 1.25, "speed_bias_mps": 0.0, "density_rmse_vpkm": 2.0}]
    ).to_csv(floor, index=False)  # fmt: skip
    assert (
        ft.main([str(base), str(pol), "--floor", str(floor), "--versus", "policy", "sumo_default"])
        == 0
    )
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[2].startswith("| `policy` | 2.121 (+0.00) | 2.121 |")  # ORDER: policy first
    assert lines[3].startswith("| `sumo_default` | 0.791 (+0.00) |")
    assert "| truth against truth | 1.250 (+0.00) |" in out
    comp = pd.concat(pd.read_csv(f / "deploy_comparison.csv") for f in (pol, base))
    gaps = ft.station_gap(comp, "policy", "sumo_default")
    assert list(gaps["arc_m"]) == [900.0, 100.0]
    # 2 intervals x (9 - 0.25) at 900 m, 2 x (0 - 1) at 100 m
    assert gaps["gap"].tolist() == pytest.approx([17.5, -2.0])


def test_a_method_in_two_folders_is_refused(tmp_path: Path) -> None:
    a = deploy_folder(tmp_path / "a", "policy", {100.0: [10.0]})
    b = deploy_folder(tmp_path / "b", "policy", {100.0: [11.0]})
    with pytest.raises(SystemExit, match="more than one folder"):
        ft.main([str(a), str(b)])

"""scripts/truth_floor.py scores one ground-truth run's stations against another's with
deploy.compare's own code: a run against itself is exact, two runs of a real SUMO truth
differ and pool as their pairs do, and bad input is one line (real SUMO on the merge of
tests/deploy/deploy_nets.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT
from deploy_nets import merge_scenario

from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section

_spec = importlib.util.spec_from_file_location("truth_floor", ROOT / "scripts" / "truth_floor.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


@pytest.fixture(scope="module")
def merge_truth(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(scenario, ground_truth folder): 2 runs of 30 + 90 s, loops of 30 s."""
    folder = tmp_path_factory.mktemp("truth_floor")
    path = merge_scenario(folder, {"warmup_s": 30.0, "duration_s": 90.0, "n_runs": 2})
    simulate_section(load_scenario(path), folder / "ground_truth", progress=False)
    return path, folder / "ground_truth"


def test_a_run_against_itself_is_exact(merge_truth) -> None:
    _, truth = merge_truth
    table = script.truth_floor(truth, 0.0, [1, 1]).set_index("pair")
    assert list(table.index) == ["1-1", "1-1", "all"]
    assert table.loc["all", "share_geh_below_5"] == 1.0
    assert table.loc["all", "share_speed_within_5pct"] == 1.0
    assert table.loc["all", "speed_rmse_mps"] == 0.0


def test_two_runs_differ_and_pool_as_their_pairs(merge_truth, tmp_path: Path, capsys) -> None:
    scen, truth = merge_truth
    out = tmp_path / "floor.csv"
    assert script.main([str(scen), str(truth), "--interval", "60", "--out", str(out)]) == 0
    table = pd.read_csv(out).set_index("pair")
    assert list(table.index) == ["0-1", "1-0", "all"]  # cyclic: each run once the truth
    assert table.loc["all", "speed_rmse_mps"] > 0.0  # another realisation is not the truth
    # Swapped, GEH and the RMSE are symmetric, the bias changes sign.
    assert table.loc["0-1", "speed_rmse_mps"] == pytest.approx(table.loc["1-0", "speed_rmse_mps"])
    assert table.loc["0-1", "speed_bias_mps"] == pytest.approx(-table.loc["1-0", "speed_bias_mps"])
    n = table.loc[["0-1", "1-0"], "station_intervals"]
    assert table.loc["all", "station_intervals"] == n.sum()
    # 60 s pools two 30 s loop intervals: fewer station-intervals than at the loops' own.
    own = script.truth_floor(truth, 0.0).set_index("pair")
    assert own.loc["all", "station_intervals"] > table.loc["all", "station_intervals"]
    assert "all" in capsys.readouterr().out


def test_bad_input_is_one_line(merge_truth, tmp_path: Path, capsys) -> None:
    scen, truth = merge_truth
    assert script.main([str(scen), str(truth), "--runs", "0", "7"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[7]" in err and "accepted" in err
    assert script.main([str(scen), str(truth), "--runs", "0"]) == 2
    assert "at least two" in capsys.readouterr().err
    assert script.main([str(scen), str(truth), "--interval", "45"]) == 2
    assert "not a multiple" in capsys.readouterr().err
    (tmp_path / "mine.csv").write_text("keep")
    assert script.main([str(scen), str(truth), "--out", str(tmp_path / "mine.csv")]) == 2
    assert (tmp_path / "mine.csv").read_text() == "keep"  # never overwritten

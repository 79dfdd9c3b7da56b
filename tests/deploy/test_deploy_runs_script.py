"""scripts/deploy_runs.py deploys a finished run's methods on every run of its ground truth:
the oracle reproduces each run exactly, each run gets its own row, and bad input is one
line (real SUMO on the merge of tests/deploy/deploy_nets.py)."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT
from deploy_nets import merge_scenario

from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section

_spec = importlib.util.spec_from_file_location("deploy_runs", ROOT / "scripts" / "deploy_runs.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


@pytest.fixture(scope="module")
def merge_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(scenario, run folder holding only its ground truth): 2 runs of 30 + 60 s."""
    folder = tmp_path_factory.mktemp("deploy_runs")
    path = merge_scenario(folder, {"warmup_s": 30.0, "duration_s": 60.0, "n_runs": 2})
    simulate_section(load_scenario(path), folder / "run" / "ground_truth", progress=False)
    return path, folder / "run"


def test_every_run_is_deployed_and_the_oracle_is_exact(merge_run, tmp_path: Path, capsys) -> None:
    scen, run = merge_run
    out = tmp_path / "out"
    argv = [str(scen), str(run), "--out", str(out), "--methods", "oracle", "sumo_default"]
    assert script.main(argv) == 0
    per_run = pd.read_csv(out / "deploy_runs.csv")
    assert sorted(per_run["run"].unique()) == [0, 1]  # both runs, not the held-out one only
    assert sorted(per_run["method"].unique()) == ["oracle", "sumo_default"]
    oracle = per_run[per_run["method"] == "oracle"]
    assert (oracle["speed_rmse_mps"] == 0.0).all() and (oracle["collisions"] == 0).all()
    summary = pd.read_csv(out / "deploy_summary.csv").set_index("method")
    assert summary.loc["oracle", "share_geh_below_5"] == 1.0
    # Each run's RMSE is over the station rows the summary scores: pooled, they give it.
    d = per_run[per_run["method"] == "sumo_default"].set_index("run")
    comp = pd.read_csv(out / "deploy_comparison.csv")
    rows = comp[(comp["method"] == "sumo_default") & (comp["lane"] == -1)]
    n = rows.dropna(subset=["speed_truth_mps", "speed_method_mps"]).groupby("run").size()
    assert n.sum() < len(comp[comp["method"] == "sumo_default"])  # lanes' rows left out
    pooled = (n * d.loc[n.index, "speed_rmse_mps"] ** 2).sum() / n.sum()
    assert pooled**0.5 == pytest.approx(summary.loc["sumo_default", "speed_rmse_mps"], rel=1e-9)
    assert set(comp["run"]) == {0, 1}
    assert not (out / "oracle" / "sumo").exists()  # SUMO's files are not kept
    assert "oracle" in capsys.readouterr().out


def test_a_set_key_that_does_not_exist_is_one_line(merge_run, tmp_path: Path, capsys) -> None:
    scen, run = merge_run
    argv = [str(scen), str(run), "--out", str(tmp_path / "o"), "--set", "deploy.nope=1"]
    assert script.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "deploy.nope=1" in err and "accepted" in err
    assert not (tmp_path / "o").exists()


def test_set_values_are_checked_as_the_scenario_file_s(merge_run, tmp_path: Path, capsys) -> None:
    """--set goes through the scenario's own checks: a value outside a field's choices is
    one line naming the file and the key (it was deployed as is), and the load-time
    default of merge_reach under merge none holds (plain, not the default occupation)."""
    scen, run = merge_run
    argv = [str(scen), str(run), "--out", str(tmp_path / "o"), "--set", "deploy.merge_reach=always"]
    assert script.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "deploy.merge_reach" in err and "'occupation'" in err, err
    assert not (tmp_path / "o").exists()
    sc = load_scenario(scen)
    none = script.changed(sc, ["deploy.merge=none"])
    assert (none.deploy.merge, none.deploy.merge_reach) == ("none", "plain")
    typed = script.changed(sc, ["deploy.safety_floor_runs=3", "deploy.command_dawdle=0.5"])
    assert typed.deploy.safety_floor_runs == 3 and typed.deploy.command_dawdle == 0.5
    assert script.changed(sc, []) is sc


def test_a_folder_with_files_is_refused(merge_run, tmp_path: Path, capsys) -> None:
    scen, run = merge_run
    (tmp_path / "mine.txt").write_text("keep")
    assert script.main([str(scen), str(run), "--out", str(tmp_path), "--methods", "oracle"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["mine.txt"]


def test_idm_detectors_drives_the_fit_of_the_run(merge_run, tmp_path: Path, capsys) -> None:
    scen, run = merge_run
    mine = tmp_path / "run"
    shutil.copytree(run / "ground_truth", mine / "ground_truth")
    argv = [str(scen), str(mine), "--methods", "idm_detectors", "oracle", "--runs", "0"]
    # Without the run's fit it is refused, not driven with the truth's own vTypes.
    assert script.main([*argv, "--out", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "idm_detectors/manifest.json: missing" in err
    theta = {"accel": 1.0, "decel": 2.0, "minGap": 2.5, "speedFactor": 0.9, "tau": 1.5}
    (mine / "deploy" / "idm_detectors").mkdir(parents=True)
    (mine / "deploy" / "idm_detectors" / "manifest.json").write_text(json.dumps({"theta": theta}))
    out = tmp_path / "out"
    assert script.main([*argv, "--out", str(out)]) == 0
    summary = pd.read_csv(out / "deploy_summary.csv").set_index("method")
    assert summary.loc["oracle", "speed_rmse_mps"] == 0.0
    assert summary.loc["idm_detectors", "speed_rmse_mps"] > 0.5  # 0.9 x the limit: slower
    assert json.loads((out / "idm_detectors" / "manifest.json").read_text())["theta"] == theta

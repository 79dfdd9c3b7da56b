"""scripts/ratio_truth.py re-runs a truth's SUMO runs with their seeds and reads each
vehicle's speedFactor (real SUMO): on a road whose vTypes have no speed deviation every
factor is the vType's, and the table sets the observed drivers' exact ratios beside them."""

from __future__ import annotations

import importlib.util

import numpy as np
import pandas as pd
from conftest import ROOT
from test_driver_ratio_censoring import capped_scenario

from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section

_spec = importlib.util.spec_from_file_location("ratio_truth", ROOT / "scripts" / "ratio_truth.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def test_the_true_factors_and_the_table(tmp_path, capsys) -> None:
    toml = capped_scenario(tmp_path)
    text = toml.read_text()
    assert "n_runs = 1" in text
    toml.write_text(text.replace("n_runs = 1", "n_runs = 3"))  # train, val, held out
    sc = load_scenario(toml)
    gt = simulate_section(sc, tmp_path / "gt", progress=False)
    tf = script.true_factors(sc, gt)
    # Every vehicle the truth recorded was re-run, at its vType's speedFactor 1 (speedDev 0).
    recorded = pd.read_csv(gt / "trajectories.csv")["vehicle_id"].unique()
    assert set(recorded) <= set(tf["vehicle_id"]) and len(recorded) >= 10
    assert np.allclose(tf["true_factor"], 1.0)
    out = tmp_path / "table.csv"
    assert script.main([str(toml), str(gt), "--csv", str(out)]) == 0
    table = pd.read_csv(out).set_index("what")
    assert table.loc["true: every vehicle seen", "median"] == 1.0
    # The cars cruise freely at their factor: their exact ratios' truth and estimate agree;
    # the trucks, held at their maxSpeed, are lower bounds.
    assert table.loc["true: exact ratio (free)", "n"] >= 5
    assert table.loc["true: lower bound", "n"] >= 5
    assert abs(table.loc["estimate kaplan_meier", "median"] - 1.0) < 0.02
    assert "true: observed" in capsys.readouterr().out

"""The pipeline from field files: the shipped Bremen example (NGSIM + PeMS, an on-ramp) is a
ground truth the later stages load, and simulate -> train-generator -> train-policy run on
a files-sourced ground truth unchanged (tiny budgets)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import BREMEN_FILES, BREMEN_TINY, bremen_files_with

from macromicro_sumo.cli import main
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.files import K_TRUE_UNKNOWN
from macromicro_sumo.truth.section import load_section_truth

EXAMPLE = BREMEN_FILES
TINY = (
    BREMEN_TINY
    + """
[evaluation]
fcd_episodes = 1
"""
)


def tiny_example(folder: Path) -> Path:
    """The shipped example with absolute paths and tiny budgets."""
    return bremen_files_with(folder, TINY)


@pytest.fixture(scope="module")
def example_truth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bremen_files") / "gt"
    assert main(["simulate", str(EXAMPLE), "--out", str(out), "--quiet"]) == 0
    return out


@pytest.mark.slow  # about 8 s of CPU: four recordings cleaned, eight report figures
def test_shipped_example_reads_into_a_ground_truth(example_truth: Path) -> None:
    sc = load_scenario(EXAMPLE)
    truth = load_section_truth(example_truth, sc)
    assert list(truth.runs) == [0, 1, 2, 3]
    assert truth.trajectories["observed"].all()
    # The on-ramp's merge lane is there: 4 lanes on E0.
    assert truth.trajectories["lane_index"].max() == 3
    assert (truth.k_estimate["k_true"] == K_TRUE_UNKNOWN).all()
    assert truth.k_estimate["k_est"].between(20, 80).all()
    manifest = json.loads((example_truth / "manifest.json").read_text())
    # Noise carries a few positions past the merge lane's end: dropped and counted.
    assert 0 < manifest["field_data"]["dropped_off_section"] < 100
    report = (example_truth / "data_report.md").read_text()
    assert "ngsim_run0.csv.gz" in report and "pems_run0.csv.gz" in report


@pytest.mark.slow
def test_generator_and_policy_stages_run_from_files(tmp_path: Path) -> None:
    """simulate (from files) -> train-generator -> train-policy, unchanged, tiny budgets."""
    path = tiny_example(tmp_path)
    gt, gen, pol = tmp_path / "gt", tmp_path / "gen", tmp_path / "pol"
    assert main(["simulate", str(path), "--out", str(gt), "--quiet"]) == 0
    assert (
        main(["train-generator", str(path), "--data", str(gt), "--out", str(gen), "--quiet"]) == 0
    )
    metrics = pd.read_csv(gen / "generator_metrics.csv")
    assert np.isfinite(metrics["speed_err_vs_psi_mps"]).all()
    args = ["--data", str(gt), "--generator", str(gen / "generator.pt"), "--out", str(pol)]
    assert main(["train-policy", str(path), *args, "--quiet"]) == 0
    manifest = json.loads((pol / "policy_manifest.json").read_text())
    assert manifest["episodes"] > 0

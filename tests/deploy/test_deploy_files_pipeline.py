"""The whole pipeline from the shipped field files (scenarios/highway_bremen_files.toml: NGSIM
+ PeMS, three lanes and an on-ramp): ground truth from files -> generator -> policy ->
evaluation against the stations and the held-out observed vehicles -> deployment against
the stations, with tiny budgets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import BREMEN_FILES, BREMEN_TINY, bremen_files_with

from macromicro_sumo.cli import main
from macromicro_sumo.deploy.compare import REFERENCE_FIELD
from macromicro_sumo.evaluation.section import REFERENCE_MICRO, REFERENCE_STATIONS, STATIONS

EXAMPLE = BREMEN_FILES
TINY = (
    BREMEN_TINY
    + """
[evaluation]
fcd_episodes = 0

[deploy]
methods = ["policy", "idm_calibrated", "oracle"]
"""
)


def tiny_example(folder: Path) -> Path:
    """The shipped example with absolute paths and tiny budgets."""
    return bremen_files_with(folder, TINY)


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("bremen_files_run")
    out = folder / "run"
    assert main(["run", str(tiny_example(folder)), "--out", str(out), "--quiet"]) == 0
    return out


@pytest.mark.slow  # about a minute: four recordings read, three policies, three deployments
def test_run_from_field_files_evaluates_and_deploys_against_the_stations(run_folder: Path):
    out = run_folder
    align = pd.read_csv(out / "evaluation" / "macro_alignment.csv")
    # Against the stations only: no observed-only "ground truth", no true hidden count.
    assert (align["reference"] == REFERENCE_STATIONS).all()
    assert set(align["hidden_count"]) == {"estimated"}
    assert "ground_truth" not in set(align["method"]) and STATIONS in set(align["method"])
    methods = align[align["method"] != STATIONS]
    assert np.isfinite(methods["station_speed_err_mps"]).all()
    assert methods["station_spacing_ratio"].between(0.5, 2.0).all()
    assert "mean_speed_err_mps" not in align  # that column is the recorded population's
    micro = pd.read_csv(out / "evaluation" / "micro_consistency.csv")
    assert (micro["reference"] == REFERENCE_MICRO).all()
    summary = pd.read_csv(out / "deploy" / "deploy_summary.csv").set_index("method")
    assert (summary["reference"] == REFERENCE_FIELD).all()
    # The route files and seeds of the exported runs: the oracle is those runs again.
    assert summary.loc["oracle", "share_geh_below_5"] == 1.0
    assert summary.loc["oracle", "speed_rmse_mps"] < 0.05
    assert summary.loc["oracle", "collisions"] == 0
    manifest = json.loads((out / "deploy" / "oracle" / "manifest.json").read_text())
    assert manifest["demand"]["source"] == "route files"
    assert (out / "report.md").is_file()


@pytest.mark.slow
def test_the_idm_fitted_to_field_pairs_deploys_without_collisions(run_folder: Path):
    """The IDM is fitted to pairs behind the leader each observed vehicle measured (NGSIM
    Preceding / Space_Headway): deployed it does not collide. Fitted to the next observed
    vehicle as the leader (the same files without Space_Headway) it collided 6 times
    (docs/field-data.md)."""
    gt = json.loads((run_folder / "ground_truth" / "manifest.json").read_text())["field_data"]
    assert gt["leader_rows_unmeasured"] == 0 and gt["leader_rows_measured"] > 10_000
    summary = pd.read_csv(run_folder / "deploy" / "deploy_summary.csv").set_index("method")
    assert summary.loc["idm_calibrated", "collisions"] == 0
    assert summary.loc["idm_calibrated", "teleports"] == 0

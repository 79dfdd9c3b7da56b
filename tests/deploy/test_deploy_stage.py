"""The deploy stage end to end: its comparison with the ground truth (deploy_comparison.csv,
deploy_summary.csv), its figures and the report's Deployment section on a small section
with an on-ramp merge; the detector-calibrated IDM on a tiny ring whose ground truth drives
IDM with known parameters."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import write_scenario
from deploy_nets import merge_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.deploy.calibrate import IDM_RANGES
from macromicro_sumo.deploy.stage import COMPARISON, HISTORY, MANIFEST, SUMMARY, deploy
from macromicro_sumo.report.deploy import deployment_section, make_deploy_plots
from macromicro_sumo.report.write import write_report
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section

SECTION_METHODS = [
    "idm_calibrated",
    "sumo_default",
    "oracle",
    "oracle_redrawn",
    "oracle_population",
]


@pytest.fixture(scope="module")
def merge_deployed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    """(ground truth, deploy folder, stage manifest) of the merge: 2 runs of 30 + 90 s."""
    folder = tmp_path_factory.mktemp("deploy_stage")
    path = merge_scenario(
        folder,
        {"warmup_s": 30.0, "duration_s": 90.0, "n_runs": 2},
        auto_spacing_m=300.0,
        deploy={"fcd_s": 30.0},
    )
    sc = load_scenario(path)
    gt = simulate_section(sc, folder / "run" / "ground_truth", progress=False)
    dep = folder / "run" / "deploy"
    m = deploy(sc, gt, None, dep, progress=False, methods=SECTION_METHODS, plots=make_deploy_plots)
    return gt, dep, m


def test_the_stage_compares_every_method_and_the_oracle_is_exact(
    merge_deployed: tuple[Path, Path, dict],
) -> None:
    _, dep, m = merge_deployed
    summary = pd.read_csv(dep / SUMMARY).set_index("method")
    assert list(summary.index) == SECTION_METHODS
    oracle = summary.loc["oracle"]
    assert oracle["station_intervals"] >= 8  # 3+ stations x 4 intervals of the held-out run
    assert oracle["share_geh_below_5"] == 1.0 and oracle["share_speed_within_5pct"] == 1.0
    assert oracle["mean_geh"] == 0.0 and oracle["speed_rmse_mps"] == 0.0
    assert oracle["density_rmse_vpkm"] == 0.0 and oracle["w1_speed_mps"] == 0.0
    comp = pd.read_csv(dep / COMPARISON)
    assert set(comp["method"]) == set(SECTION_METHODS)
    o = comp[comp["method"] == "oracle"]
    assert (o["geh"] == 0.0).all() and (o["flow_truth_vph"] == o["flow_method_vph"]).all()
    # Switching every driven vehicle to SUMO's defaults changes the detectors somewhere.
    assert summary.loc["sumo_default", "speed_rmse_mps"] > 0.0
    # The merge's Krauss cars dawdle: with SUMO's random streams re-mapped the same drivers
    # give other detector figures, with nothing driven and no collision.
    redrawn = summary.loc["oracle_redrawn"]
    assert redrawn["speed_rmse_mps"] > 0.0 and redrawn["collisions"] == 0
    assert redrawn["vehicle_steps_driven"] == 0
    assert json.loads((dep / "oracle_redrawn" / "manifest.json").read_text())["rng_streams"] == 1
    # Each car's own speedFactor redrawn from its vType's too: here further from the truth.
    population = summary.loc["oracle_population"]
    assert population["speed_rmse_mps"] > redrawn["speed_rmse_mps"]
    assert population["collisions"] == 0 and population["vehicle_steps_driven"] == 0
    # The manifest lists the comparison and the figures with their sizes.
    outputs = json.loads((dep / MANIFEST).read_text())["outputs"]
    for name in (COMPARISON, SUMMARY, "plots/deploy_fundamental_diagram.png"):
        assert name in outputs and (dep / name).stat().st_size == outputs[name]["bytes"]
    assert m["methods"] == SECTION_METHODS


def test_the_deployment_section_names_every_method(
    merge_deployed: tuple[Path, Path, dict],
) -> None:
    _, dep, _ = merge_deployed
    text = "\n".join(deployment_section(dep.parent))
    assert text.startswith("## Deployment")
    for name in SECTION_METHODS:
        assert f"| {name} " in text
    assert "![deploy_fundamental_diagram](deploy/plots/deploy_fundamental_diagram.png)" in text
    assert deployment_section(dep) == []  # a folder without a deployment: no section


@pytest.fixture(scope="module")
def known_ring(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The paper ring (5 vehicles, 4 runs of 120 s) whose fleet drives IDM with one set of
    parameters: speed factor 0.85 (the fit starts at 1.0, the middle of its range)."""
    folder = tmp_path_factory.mktemp("known_ring")
    fixed = {"accel_mps2": 1.0, "decel_mps2": 1.5, "tau_s": 1.2, "min_gap_m": 2.0}
    table = {f"fleet.{k}": [v, v] for k, v in fixed.items()}
    table |= {
        "fleet.speed_factor": [0.85, 0.85],
        "simulation.n_runs": 4,
        "simulation.duration_s": 120.0,
        # The evaluation count ends the fit, not the clock: the same result on a loaded machine.
        "deploy.calibration_budget_s": 3600.0,
        "deploy.calibration_evals": 24,
    }
    path = write_scenario(folder / "s", table)
    gt = folder / "run" / "ground_truth"
    assert main(["simulate", str(path), "--out", str(gt), "--quiet"]) == 0
    return path, gt


def test_idm_detectors_moves_towards_the_truths_parameters(
    known_ring: tuple[Path, Path],
) -> None:
    path, gt = known_ring
    sc = load_scenario(path)
    out = gt.parent / "deploy"
    m = deploy(
        sc,
        gt,
        None,
        out,
        progress=False,
        methods=["idm_detectors", "oracle", "oracle_redrawn", "oracle_population"],
    )
    cal = m["idm_detectors"]
    assert set(cal["training_runs"]).isdisjoint(m["held_out_runs"])
    assert cal["loss"] < 0.5 * cal["start_loss"], cal
    start = np.mean(IDM_RANGES["speedFactor"])
    assert abs(cal["params"]["speedFactor"] - 0.85) < 0.5 * abs(start - 0.85), cal["params"]
    history = pd.read_csv(out / "idm_detectors" / HISTORY)
    assert len(history) == cal["evaluations"] <= 24
    assert history["loss"].min() == pytest.approx(cal["loss"])
    method = json.loads((out / "idm_detectors" / "manifest.json").read_text())
    assert method["theta"]["speedFactor"] == cal["params"]["speedFactor"]
    # delta is SUMO's 4 (not fitted, not written): the fleet's own.
    assert method["theta"].get("delta", 4.0) == sc.fleet.delta
    # Deployed on the held-out runs, the fit is closer to the truth than its start point.
    summary = pd.read_csv(out / SUMMARY).set_index("method")
    assert summary.loc["idm_detectors", "share_speed_within_5pct"] >= 0.9
    # SUMO's IDM draws nothing: its random streams re-mapped, the ring repeats its truth.
    assert summary.loc["oracle_redrawn", "speed_rmse_mps"] == 0.0
    # One set of parameters: its drivers are its population, and redrawn it repeats too.
    assert summary.loc["oracle_population", "speed_rmse_mps"] == 0.0
    # The report says how the fit ended: here the count or convergence, never the clock.
    (line,) = [x for x in deployment_section(gt.parent) if x.startswith("- `idm_detectors`")]
    assert f"in {cal['evaluations']} whole-run evaluation(s)" in line
    assert cal["stopped_by"] in ("evaluations", "converged") and "wall-clock" not in line
    # report.md of the run folder gets the Deployment section.
    report = write_report(sc, gt.parent, {}).read_text()
    assert "## Deployment" in report and "| idm_detectors " in report and "| oracle " in report

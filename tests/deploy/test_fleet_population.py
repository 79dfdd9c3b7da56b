"""Who a section's deployment drives: with ``instrumented.hidden = "snapshot"`` (every vehicle
recorded, K random ones hidden per snapshot: nobody instrumented for good) the whole fleet, as
the ring deploys it; otherwise every vehicle that is not instrumented; ``deploy.share`` and
``deploy.vtype`` narrow either. A small fleet on the ring network as a closed section, real
SUMO runs."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from fleet_scenarios import small_fleet_table, write_fleet_scenario

from macromicro_sumo.deploy.population import in_share, population_scenario, whole_fleet
from macromicro_sumo.deploy.stage import MANIFEST, SUMMARY, deploy
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import is_instrumented, simulate_section

N = 4
METHODS = ["sumo_default", "oracle"]


@pytest.fixture(scope="module")
def fleet_truth(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(folder, ground truth) of 2 runs of 60 s of a 4-vehicle fleet."""
    folder = tmp_path_factory.mktemp("fleet_population")
    sc = load_scenario(write_fleet_scenario(folder, small_fleet_table(N, n_runs=2)))
    return folder, simulate_section(sc, folder / "gt", progress=False)


def deployed(folder: Path, gt: Path, name: str, **tables: dict) -> tuple[pd.DataFrame, dict]:
    """(runs.csv of sumo_default, the stage manifest) of a deployment of the variant."""
    table = small_fleet_table(N, n_runs=2, **tables)
    sc = load_scenario(write_fleet_scenario(folder, table, f"{name}.toml"))
    out = folder / name
    deploy(sc, gt, None, out, progress=False, methods=METHODS)
    return pd.read_csv(out / "sumo_default" / "runs.csv"), json.loads((out / MANIFEST).read_text())


def truth_rows(gt: Path, run: int) -> pd.DataFrame:
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str})
    return traj[traj["run"] == run]


def driven_per_step(rows: pd.DataFrame, runs: pd.DataFrame, run: int) -> float:
    """Vehicles driven per step of ``run`` after the first (which inserts the fleet: the
    drivers act before each step, when nobody is on the road yet)."""
    steps = rows["time_s"].nunique() - 1
    return float(runs.loc[runs["run"] == run, "vehicle_steps_driven"].iloc[0]) / steps


def test_per_snapshot_hidden_sets_deploy_the_whole_fleet(fleet_truth) -> None:
    folder, gt = fleet_truth
    runs, manifest = deployed(folder, gt, "snapshot")
    (run,) = manifest["held_out_runs"]
    rows = truth_rows(gt, run)
    # Instrumented and not alike: the truth has both, the deployment drives all N.
    assert 0 < rows.groupby("vehicle_id")["observed"].first().sum() < N
    assert driven_per_step(rows, runs, run) == N
    assert manifest["population"].startswith("every vehicle (instrumented.hidden")
    summary = pd.read_csv(folder / "snapshot" / SUMMARY).set_index("method")
    assert summary.loc["oracle", "speed_rmse_mps"] == 0.0  # nobody driven: the truth itself
    assert summary.loc["sumo_default", "speed_rmse_mps"] > 0.0


def test_per_run_hidden_sets_keep_the_instrumented_vehicles(fleet_truth) -> None:
    folder, gt = fleet_truth
    runs, manifest = deployed(folder, gt, "per_run", instrumented={"hidden": "run"})
    (run,) = manifest["held_out_runs"]
    rows = truth_rows(gt, run)
    not_instrumented = int((~rows.groupby("vehicle_id")["observed"].first()).sum())
    assert driven_per_step(rows, runs, run) == not_instrumented
    assert manifest["population"] == "every vehicle that is not instrumented"


def test_share_and_vtype_narrow_the_whole_fleet(fleet_truth) -> None:
    folder, gt = fleet_truth
    runs, manifest = deployed(folder, gt, "share", deploy={"share": 0.5})
    (run,) = manifest["held_out_runs"]
    rows = truth_rows(gt, run)
    ids = rows["vehicle_id"].unique()
    chosen = sum(in_share(2024, run, v, 0.5) for v in ids)
    assert chosen < N  # the hash leaves some out here, so the figure below could fail
    assert driven_per_step(rows, runs, run) == chosen
    assert "a share 0.5" in manifest["population"]
    # The fleet has one vType per vehicle: deploy.vtype picks that one vehicle.
    runs, manifest = deployed(folder, gt, "vtype", deploy={"vtype": "v2"})
    assert driven_per_step(rows, runs, run) == 1
    assert "of vType 'v2'" in manifest["population"]


def test_population_scenario_instruments_nobody_only_for_snapshot_sets(fleet_truth) -> None:
    folder, _ = fleet_truth
    snap = load_scenario(write_fleet_scenario(folder, small_fleet_table(N), "s.toml"))
    per_run = load_scenario(
        write_fleet_scenario(folder, small_fleet_table(N, hidden="run"), "r.toml")
    )
    assert whole_fleet(snap) and not whole_fleet(per_run)
    assert population_scenario(per_run) is per_run
    dep = population_scenario(snap)
    ids = [f"v{i}" for i in range(N)]
    assert any(is_instrumented(snap, v, v, 0) for v in ids)
    assert not any(is_instrumented(dep, v, v, r) for v in ids for r in range(40))
    # Stage II's settings stay: only who is instrumented changes.
    assert dep.instrumented.hidden == "snapshot" and dep.policy == snap.policy

"""The deployment's plots and report section: PNG files written from real ground-truth
folders and hand-made trajectories, and the markdown's table and plain-words verdicts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import SMALL, write_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.deploy.compare import (
    REFERENCE_FIELD,
    REFERENCE_SIMULATED,
    SUMMARY_COLUMNS,
    acted_shares,
    compare_folders,
)
from macromicro_sumo.report.deploy import (
    FLOORS,
    deployment_markdown,
    make_deploy_plots,
    plot_speed_heatmaps,
)
from macromicro_sumo.report.plots import plot_time_space

PNG = b"\x89PNG\r\n\x1a\n"


def is_png(path: Path) -> bool:
    return path.is_file() and path.stat().st_size > 1000 and path.read_bytes()[:8] == PNG


@pytest.fixture(scope="module")
def rings(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two ground truths of the paper ring (2 runs of 120 s): the truth and a stand-in."""
    folder = tmp_path_factory.mktemp("deploy_report")
    outs = []
    for seed in (42, 7):
        path = write_scenario(folder / f"s{seed}", {**SMALL, "seed": seed})
        assert main(["simulate", str(path), "--out", str(folder / f"gt{seed}"), "--quiet"]) == 0
        outs.append(folder / f"gt{seed}")
    return outs[0], outs[1]


def test_plots_from_real_folders(rings: tuple[Path, Path], tmp_path: Path) -> None:
    truth, other = rings
    methods = {"policy": other, "oracle": truth}
    comparison, _ = compare_folders(truth, methods)
    made = make_deploy_plots(truth, methods, comparison, tmp_path / "plots")
    assert [p.name for p in made] == [
        "deploy_fundamental_diagram.png",
        "deploy_speed_heatmap.png",
        "deploy_time_space.png",
    ]
    assert all(is_png(p) for p in made)


def test_lane_plots_of_a_two_lane_road(tmp_path: Path) -> None:
    # Two vehicles, one per lane, 20 s at 1 s steps; the method's lane-1 vehicle is slower.
    t = np.arange(20.0)

    def frame(v1: float) -> pd.DataFrame:
        return pd.DataFrame(
            {
                "run": 0,
                "time_s": np.concatenate([t, t]),
                "vehicle_id": ["a"] * 20 + ["b"] * 20,
                "lane_index": [0] * 20 + [1] * 20,
                "arc_m": np.concatenate([10.0 * t, 5.0 + v1 * t]),
                "speed_mps": np.concatenate([np.full(20, 10.0), np.full(20, v1)]),
            }
        )

    lanes = {"ground_truth": frame(12.0), "policy": frame(8.0)}
    assert is_png(plot_speed_heatmaps(lanes, tmp_path / "heat.png", run=0, time_bin_s=5.0))
    assert is_png(plot_time_space(lanes, tmp_path / "ts.png", run=0))
    with pytest.raises(ValueError, match="run 3"):
        plot_speed_heatmaps(lanes, tmp_path / "none.png", run=3)


def summary() -> pd.DataFrame:
    rows = [
        # policy: 90% GEH (met), 80% speed (missed), speed RMSE 0.42
        ("policy", 0.90, 0.80, 0.42, 3.0, 0.0, 0.0),
        ("idm_detectors", 0.95, 0.80, 0.30, 4.0, 0.0, 0.0),
        ("oracle", 0.85, 0.70, 0.50, 5.0, 0.0, 0.0),
        ("sumo_default", 0.60, 0.40, 0.90, 6.0, 2.0, 1.0),
        ("idm_calibrated", 0.88, 0.75, 0.40, 3.5, 0.0, 0.0),
    ]
    df = pd.DataFrame(
        rows,
        columns=[
            "method",
            "share_geh_below_5",
            "share_speed_within_5pct",
            "speed_rmse_mps",
            "density_rmse_vpkm",
            "collisions",
            "teleports",
        ],
    )
    return df.assign(runs=2, truth_collisions=0.0, truth_teleports=0.0).reindex(
        columns=SUMMARY_COLUMNS
    )


def test_markdown_names_every_method_and_its_numbers() -> None:
    md = deployment_markdown(summary(), ["plots/deploy_speed_heatmap.png"])
    assert md.startswith("## Deployment\n")
    table = {line.split(" | ")[0].strip("| "): line for line in md.splitlines() if "|" in line}
    for method, geh_pct, rmse in (
        ("policy", "90.0", "0.420"),
        ("idm_detectors", "95.0", "0.300"),
        ("oracle", "85.0", "0.500"),
        ("sumo_default", "60.0", "0.900"),
        ("idm_calibrated", "88.0", "0.400"),
    ):
        assert f"| {geh_pct} |" in table[method] and f"| {rmse} |" in table[method]
    assert "flow GEH < 5 in 90.0% of station-intervals (target at least 85%): met." in md
    assert "mean speed within 5% in 80.0% of station-intervals (target at least 85%): missed" in md
    # The fitted IDM beats the policy on speed RMSE (0.400 < 0.420), the defaults do not.
    assert "(`idm_calibrated`) 0.400 m/s: the policy is not better." in md
    assert "(`sumo_default`) 0.900 m/s: the policy is better." in md
    # Where the detector-calibrated IDM is ahead, and by how much.
    assert (
        "The detector-calibrated IDM (`idm_detectors`) is ahead of the policy on: GEH < 5 by "
        "5.0 percentage points (95.0% vs 90.0%); speed RMSE by 0.120 m/s (0.300 vs 0.420)."
    ) in md
    assert "The policy is ahead of it on: density RMSE." in md
    assert "The oracle (`oracle`) is ahead of the policy on nothing." in md
    assert "- `sumo_default`: 2 collisions and 1 teleports the ground truth does not have." in md
    assert "![deploy_speed_heatmap](plots/deploy_speed_heatmap.png)" in md


def with_safety(df: pd.DataFrame) -> pd.DataFrame:
    """The policy drove 2,000 vehicle-steps; its safety layer lowered 150 and raised 8."""
    counts = {"vehicle_steps_driven": 2000.0, "safety_acted": 150.0, "floor_acted": 8.0}
    row = {**counts, **acted_shares(counts)}
    df = df.copy()
    for col, value in row.items():
        df[col] = df[col].astype(float)
        df.loc[df["method"] == "policy", col] = value
    return df


def test_markdown_says_how_often_the_safety_layer_acted() -> None:
    md = deployment_markdown(with_safety(summary()))
    head = next(line for line in md.splitlines() if line.startswith("| method"))
    assert "safety lowered (% of driven)" in head and "floor raised (% of driven)" in head
    policy = next(line for line in md.splitlines() if line.startswith("| policy"))
    assert policy.endswith("| 2000 | 7.5 | 0.4 |")  # 150 / 2000 and 8 / 2000
    assert (
        "- `policy`: of 2,000 driven vehicle-steps, the safety layer lowered the command to "
        "the safe speed behind the leader in 150 (7.5%) and raised it to its floor (20% of "
        "the lane's limit) in 8 (0.4%)."
    ) in md
    # Methods that drove nothing through it (a vType switch, the oracle) get no such line.
    assert md.count("driven vehicle-steps, the safety layer") == 1


def test_markdown_says_what_each_data_source_is_compared_with() -> None:
    sim = deployment_markdown(summary().assign(reference=REFERENCE_SIMULATED))
    assert "same demand, same seeds" in sim and "Field data" not in sim
    assert f"Reference (`reference`): {REFERENCE_SIMULATED}." in sim
    assert "- Ground truth over the same runs: 0 collisions, 0 teleports." in sim
    assert "2 collisions and 1 teleports the ground truth does not have." in sim
    field = deployment_markdown(summary().assign(reference=REFERENCE_FIELD))
    # Field data has no held-out runs to re-run and counts no collisions of its own.
    assert "same seeds" not in field and "ground truth" not in field
    assert "against the field stations' measurements" in field
    assert "W1 speed and accel are against the observed vehicles" in field
    assert "headway and TTC are not compared" in field
    assert f"Reference (`reference`): {REFERENCE_FIELD}." in field
    assert "- Field data records no collisions or teleports" in field
    assert "- `sumo_default`: 2 collisions and 1 teleports in SUMO." in field


@pytest.mark.parametrize(("floor", "out_of_reach"), [(0.6, True), (0.9, False)])
def test_the_targets_are_read_against_the_floors(floor: float, out_of_reach: bool) -> None:
    s = summary()
    rows = [s[s["method"] == "oracle"].assign(method=m) for m in FLOORS]
    for row, share, rmse in zip(rows, (0.95, floor), (0.2, 0.35), strict=True):
        row[["share_geh_below_5", "share_speed_within_5pct", "speed_rmse_mps"]] = [
            share,
            share,
            rmse,
        ]
    md = deployment_markdown(pd.concat([s, *rows], ignore_index=True))
    assert md.count("(`oracle_redrawn`) reaches 95.0%.") == 2
    assert md.count(f"(`oracle_population`) reaches {100 * floor:.1f}%") == 2
    assert md.count("out of its reach here at this interval") == (2 if out_of_reach else 0)
    assert "(`oracle_redrawn`): 0.200 m/s (the policy's: 0.420 m/s)." in md
    assert "(`oracle_population`): 0.350 m/s" in md
    # Without them the report says nothing of a floor.
    assert "oracle_redrawn" not in deployment_markdown(s)

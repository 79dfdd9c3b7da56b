"""The one report writer on a ring run folder that holds only some stages' CSVs: the parts
whose CSVs exist, in the ring's order, with figures computed from them; nothing else."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
from conftest import PAPER_SCENARIO

from macromicro_sumo.report.write import write_report
from macromicro_sumo.scenario.load import load_scenario


def _alignment() -> pd.DataFrame:
    """K = 1: the ground truth, the policy 0.05 m/s slow (its interval clear of zero) and
    micro_only 0.01 m/s slow (its interval overlapping the policy's)."""
    row = {"K": 1, "mean_spacing_m": 125.66, "collisions": 0, "w1_speed_mps": 0.0}
    rows = [
        {**row, "method": "ground_truth", "mean_speed_mps": 11.80, "std_speed_mps": 0.16},
        {**row, "method": "policy", "mean_speed_mps": 11.75, "std_speed_mps": 0.20},
        {**row, "method": "micro_only", "mean_speed_mps": 11.79, "std_speed_mps": 0.16},
    ]
    df = pd.DataFrame(rows).assign(std_spacing_m=22.3)
    df["mean_speed_err_mps"] = (df["mean_speed_mps"] - 11.80).abs()
    df["speed_err_ci_lo_mps"] = df["mean_speed_err_mps"] - 0.045
    df["speed_err_ci_hi_mps"] = df["mean_speed_err_mps"] + 0.045
    return df


def test_ring_report_shows_the_parts_its_csvs_allow_in_order(tmp_path: Path) -> None:
    sc = load_scenario(PAPER_SCENARIO)
    (tmp_path / "evaluation").mkdir()
    _alignment().to_csv(tmp_path / "evaluation" / "macro_alignment.csv", index=False)
    micro = pd.DataFrame(
        {"method": ["policy", "micro_only"], "nll": [-0.19, -0.20], "action_rmse_mps2": [0.3, 0.4]}
    )
    micro.to_csv(tmp_path / "evaluation" / "micro_consistency.csv", index=False)
    text = write_report(sc, tmp_path, {"timings_s": {"evaluate": 1.5}, "seed": 3}).read_text()
    headings = [line for line in text.splitlines() if line.startswith("## ")]
    assert headings == [
        f"## Macro alignment (held-out scenes, rollouts of {sc.evaluation.horizon_steps} x "
        f"{sc.simulation.step_length_s:g} s)",
        "## Micro consistency (held-out observed actions)",
        "## Which method wins each figure",
        "## Manifest",
    ]
    assert text.startswith(f"# macromicro-sumo report: {sc.name}\n")
    # The registry's words for the methods present, the paper's policy beside ours.
    assert "- `micro_only` (learned): ablation" in text and "| 1 | paper policy | 11.55 |" in text
    # Targets: the policy's speed error and spread against the ground truth's.
    assert "| 1 | 0.050 | 25.000 |" in text
    # Intervals overlap: the mean-speed figure is a tie; micro_only's NLL is lower, the
    # policy's action RMSE.
    assert "| mean-speed error (m/s) | 1 | micro_only | 0.0100 | 0.0500 | 0.0100 | tie" in text
    assert (
        "| micro NLL | held-out | micro_only | -0.2000 | -0.1900 | -0.2000 | micro_only |" in text
    )
    assert "| action RMSE (m/s2) | held-out | policy | 0.3000 | 0.3000 | 0.4000 | policy |" in text
    manifest = text.split("```json\n")[1].split("```")[0]
    assert json.loads(manifest) == {"timings_s": {"evaluate": 1.5}, "seed": 3}
    # No plot had its inputs: no plots folder, no Plots part.
    assert not (tmp_path / "plots").exists()

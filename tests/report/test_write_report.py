"""The report's paper part on a ring run folder: the paper's policy and ground truth beside
ours, and the targets, from the by-K table; only on the paper's ring."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
from conftest import PAPER_SCENARIO

from macromicro_sumo.report.write import Run, paper_part
from macromicro_sumo.scenario.load import load_scenario


def _by_k() -> pd.DataFrame:
    """K = 1, both hidden-count labels: the ground truth, the policy 0.05 m/s slow."""
    row = {"K": 1, "mean_spacing_m": 125.66, "collisions": 0, "std_spacing_m": 22.3}
    rows = [
        {**row, "method": "ground_truth", "mean_speed_mps": 11.80, "std_speed_mps": 0.16},
        {**row, "method": "policy", "mean_speed_mps": 11.75, "std_speed_mps": 0.20},
    ]
    df = pd.DataFrame(rows)
    return pd.concat([df.assign(hidden_count="estimated"), df.assign(hidden_count="true")])


def _run(folder: Path, length_m: float) -> Run:
    (folder / "evaluation").mkdir(parents=True)
    (folder / "ground_truth").mkdir()
    _by_k().to_csv(folder / "evaluation" / "macro_alignment_by_k.csv", index=False)
    manifest = {"section_length_m": length_m}
    (folder / "ground_truth" / "manifest.json").write_text(json.dumps(manifest))
    return Run(load_scenario(PAPER_SCENARIO), folder, {})


def test_the_paper_ring_shows_the_papers_policy_and_the_targets(tmp_path: Path) -> None:
    text = "\n".join(paper_part(_run(tmp_path, 628.3185)))
    assert "| 1 | paper policy | 11.55 |" in text
    # Targets: the policy's speed error and spread against the ground truth's, once per K
    # (the estimated hidden count's rows).
    assert "| 1 | 0.050 | 25.000 |" in text and text.count("| 1 | 0.050 |") == 1


def test_another_ring_has_no_paper_part(tmp_path: Path) -> None:
    assert paper_part(_run(tmp_path, 230.0)) == []

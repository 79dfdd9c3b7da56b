"""report.md's line on the detector-calibrated IDM's fit (``report.deploy_manifest_lines``): how many
whole-run evaluations, the loss, and what ended the fit; where the wall clock ended it, the
line warns that a busier machine gets another baseline."""

from __future__ import annotations

import json
from pathlib import Path

from macromicro_sumo.deploy.stage import MANIFEST
from macromicro_sumo.report.deploy_manifest_lines import calibration_line, with_manifest_lines

# The ring's record at load 19 (stop 51): 18 evaluations in the 300 s budget.
RECORD = {
    "evaluations": 18,
    "loss": 0.1470,
    "start_loss": 0.3086,
    "stopped_by": "budget",
    "training_runs": list(range(24)),
    "wall_s": 302.4,
}


def test_a_fit_the_clock_ended_says_so():
    line = calibration_line(RECORD)
    assert line.startswith("- `idm_detectors`: IDM fitted to the detectors of 24 training run(s)")
    assert "in 18 whole-run evaluation(s), loss 0.309 -> 0.147" in line
    assert "`deploy.calibration_budget_s` ended it after 302 s" in line
    assert "busier machine" in line


def test_a_fit_the_count_ended_is_the_same_anywhere():
    line = calibration_line(RECORD | {"stopped_by": "evaluations", "evaluations": 30})
    assert "in 30 whole-run evaluation(s)" in line and "any machine" in line
    assert "wall-clock" not in line


def test_the_line_goes_before_the_figures_and_only_with_a_fit(tmp_path: Path):
    lines = ["## Deployment", "", "- the policy: met.", "", "![fd](deploy/plots/fd.png)"]
    assert with_manifest_lines(lines, tmp_path) == lines  # no manifest: as they are
    (tmp_path / MANIFEST).write_text(json.dumps({"idm_detectors": RECORD}))
    out = with_manifest_lines(lines, tmp_path)
    assert out[:3] == lines[:3] and out[3] == calibration_line(RECORD) and out[4:] == lines[3:]
    (tmp_path / MANIFEST).write_text(json.dumps({"methods": ["policy"]}))
    assert with_manifest_lines(lines, tmp_path) == lines

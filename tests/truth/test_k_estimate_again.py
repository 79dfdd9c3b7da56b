"""scripts/k_estimate_again.py estimates K of a finished ground truth as ``simulate`` wrote
it (real SUMO: the merge with a lane drop of test_hidden_count): the same bytes, so a
changed md5 after an edit to truth/ is the edit's, and the figures printed are k_summary's."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
from conftest import ROOT
from test_hidden_count import merge_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.section_macro import k_summary

_spec = importlib.util.spec_from_file_location(
    "k_estimate_again", ROOT / "scripts" / "k_estimate_again.py"
)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def test_the_estimate_again_is_the_one_simulate_wrote(tmp_path: Path) -> None:
    toml = merge_scenario(tmp_path, 1300.0, 400.0, 6.0, boundary=True)
    gt = tmp_path / "gt"
    assert main(["simulate", str(toml), "--out", str(gt), "--quiet"]) == 0
    k, md5, own = script.again(toml, gt)
    assert md5 == own
    written = pd.read_csv(gt / "k_estimate.csv")
    np.testing.assert_array_equal(k["k_est"], written["k_est"])
    assert k["congested"].notna().all() and k["congested"].any()  # the lane drop queues
    row = script.line(toml, gt)
    per_lane = k_summary(written, Section.read(gt / "section.json"))["mean_abs_error_per_lane_veh"]
    assert f"K/lane {per_lane:.2f}" in row and row.endswith("(unchanged)"), row
    assert script.main([str(toml)]) == 2  # a scenario without its ground truth

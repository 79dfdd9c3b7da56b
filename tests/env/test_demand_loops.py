"""SUMO's own induction loops in a demand core's run (``DemandCore.loop_table``): with every
vehicle left to SUMO's models, the truth's run driven again reads on its detectors what
the truth's ``detectors.csv`` holds, counts and speeds, on a closed ring whose fleet is
inserted standing over loops and on an open multi-lane merge with a lane drop. Real SUMO,
small runs."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import merge_scenario  # noqa: E402

from macromicro_sumo.env.demand import DemandCore  # noqa: E402
from macromicro_sumo.errors import UserError  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402

KEY = ["detector_id", "begin_s", "end_s"]


@pytest.fixture(scope="module")
def ring(ring_two_lane_short):
    """ring_two_lane, one run: a 60 s warm-up, 60 s recorded; its loops every 60 s."""
    return ring_two_lane_short


@pytest.fixture(scope="module")
def merge(tmp_path_factory: pytest.TempPathFactory):
    """The merge (2 -> 3 -> 2 lanes, an on-ramp, a lane drop), 2 runs of 30 s + 60 s, loops
    every 200 m on every lane, 30 s intervals."""
    folder = tmp_path_factory.mktemp("merge_loops")
    sc = load_scenario(merge_scenario(folder, {"warmup_s": 30.0, "duration_s": 60.0, "n_runs": 2}))
    gt = simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(gt, sc)


def assert_same_table(table: pd.DataFrame, truth: pd.DataFrame) -> None:
    """Every row of the truth's run in the table and none more: counts exact, speeds to
    SUMO's output precision (the same file format, read the same way)."""
    assert list(table.columns) == list(truth.columns)
    both = truth.merge(table, on=KEY, how="outer", suffixes=("", "_core"), indicator=True)
    assert (both["_merge"] == "both").all(), both.loc[both["_merge"] != "both", KEY]
    np.testing.assert_array_equal(both["n_veh_core"], both["n_veh"])
    np.testing.assert_allclose(both["speed_mps_core"], both["speed_mps"], atol=0.006)
    np.testing.assert_allclose(both["occupancy_pct_core"], both["occupancy_pct"], atol=0.006)


def test_the_ring_read_by_sumos_loops_is_the_truths_standing_start_included(ring) -> None:
    sc, truth = ring
    det = truth.detectors[truth.detectors["run"] == 0]
    loops = det.drop_duplicates("detector_id")
    core = DemandCore(sc, truth, np.array([0]), 10)
    try:
        core.reset(0, core.dt, loops=True)  # the fleet's insertion step
        # The premise: a vehicle stands over a loop on its lane (its back before the loop,
        # its front past it), the case a passage read off positions got 0.5 m/s wrong.
        over = 0
        for v, (lane_id, pos, speed, _) in core.lane_states().items():
            lane, arc = core.section.locate(lane_id, pos)
            length = core.vtypes[core.types[v]].length_m
            on = (loops["lane_index"] == lane) & (loops["arc_m"] <= arc)
            over += int(speed == 0.0 and (on & (loops["arc_m"] > arc - length)).any())
        assert over >= 1
        end_s = sc.simulation.warmup_s + sc.simulation.duration_s
        for _ in range(int(round(end_s / core.dt)) - 1):  # nobody observed: none commanded
            core.step(np.zeros(0))
        table = core.loop_table()
    finally:
        core.close()
    assert det["n_veh"].sum() > 100  # the fleet passes the loops
    assert_same_table(table, det)


def test_an_open_multi_lane_section_read_by_sumos_loops_is_the_truths(merge) -> None:
    sc, truth = merge
    end_s = sc.simulation.warmup_s + sc.simulation.duration_s
    core = DemandCore(sc, truth, truth.runs, 10)
    try:
        for run in truth.runs:
            core.reset(int(run), end_s, loops=True)
            det = truth.detectors[truth.detectors["run"] == run]
            assert det["lane_index"].nunique() == 3 and det["n_veh"].sum() > 50
            assert_same_table(core.loop_table(), det)
        # Without loops the core keeps PPO's episodes as they were: nothing to read.
        core.reset(int(truth.runs[0]), 30.0)
        with pytest.raises(RuntimeError, match="loops=True"):
            core.loop_table()
        # A run ended inside an interval: that interval up to the end, no more vehicles.
        core.reset(int(truth.runs[0]), 45.0, loops=True)
        table = core.loop_table()
    finally:
        core.close()
    assert table["end_s"].max() == pytest.approx(45.0)
    last = table[table["end_s"] == table["end_s"].max()]
    det = truth.detectors[truth.detectors["run"] == truth.runs[0]]
    assert last["begin_s"].eq(30.0).all()
    full = det[det["begin_s"] == 30.0].set_index("detector_id")["n_veh"]
    assert (last.set_index("detector_id")["n_veh"] <= full.loc[last["detector_id"]]).all()


def test_a_truth_from_another_scenario_is_refused(merge, tmp_path: Path) -> None:
    """Loops every 150 m are not the truth's (every 200 m): the error names the file."""
    sc, truth = merge
    other = replace(sc, detectors=replace(sc.detectors, auto_spacing_m=150.0))
    core = DemandCore(other, truth, truth.runs, 10)
    try:
        with pytest.raises(UserError, match=r"detectors\.csv: detector_id holds"):
            core.reset(int(truth.runs[0]), 10.0, loops=True)
    finally:
        core.close()

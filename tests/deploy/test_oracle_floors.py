"""The targets' floors on the paper ring's heterogeneous fleet: ``oracle_population`` redraws
each driver's own IDM parameters from the ``[fleet]`` ranges (the ring's truth is SUMO's IDM,
which draws nothing, so ``oracle_redrawn`` repeats it exactly)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
from conftest import SMALL_RING, write_scenario

from macromicro_sumo.deploy.stage import SUMMARY, deploy
from macromicro_sumo.scenario.load import load_scenario

FLOORS = ["oracle", "oracle_redrawn", "oracle_population"]
COLUMNS = ["share_geh_below_5", "share_speed_within_5pct", "speed_rmse_mps", "collisions"]


def test_the_population_floor_redraws_the_drivers_and_repeats_with_the_seed(
    small_ring_gt: Path, tmp_path: Path
) -> None:
    sc = load_scenario(write_scenario(tmp_path / "s", SMALL_RING))
    summaries = []
    for name in ("a", "b"):
        deploy(sc, small_ring_gt, None, tmp_path / name, progress=False, methods=FLOORS)
        summaries.append(pd.read_csv(tmp_path / name / SUMMARY).set_index("method")[COLUMNS])
    s = summaries[0]
    assert s.loc["oracle", "speed_rmse_mps"] == 0.0
    assert s.loc["oracle_redrawn", "speed_rmse_mps"] == 0.0
    # Other drivers of the same population: other speeds, no collision.
    assert s.loc["oracle_population", "speed_rmse_mps"] > 0.01
    assert (s["collisions"] == 0).all()
    pd.testing.assert_frame_equal(summaries[0], summaries[1])

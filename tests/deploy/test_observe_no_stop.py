"""``deploy.observe.observe_rows`` skips ``nearer_standing`` where no driven vehicle has a
stop ahead (every stop inf or NaN: nothing can be nearer than its leader; every step of
Bremen's section). Its results are bit for bit those of the full path, which a stop far
beyond every leader (never nearer) forces."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "road"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_observe_buffers import _step  # noqa: E402
from test_section_leaders import EDGES, build_merge_net  # noqa: E402

from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table, observe_rows  # noqa: E402
from macromicro_sumo.road.physics import LEADER_COLUMN  # noqa: E402
from macromicro_sumo.road.section import read_section  # noqa: E402


@pytest.mark.parametrize("stop_gap_m", [None, 2.0])
@pytest.mark.parametrize("observation", ["lookahead_gap", "lookahead"])
def test_no_stop_ahead_gives_the_full_paths_results(
    tmp_path: Path, observation: str, stop_gap_m: float | None
) -> None:
    sec = read_section(build_merge_net(tmp_path, (20.0, 25.0, 30.0)), EDGES, closed=False)
    shapes = Table.of_rows({**{f"v{i}": (5.0, 3.0, 4.5) for i in range(9)},
                            "truck": (12.0, 2.5, 4.0)}, STANDING)  # fmt: skip
    vids, rows, lanes, st, leaders, _ = _step(9)
    none = np.full(len(vids), np.inf)
    none[2] = np.nan  # NaN: no signal at all, as inf
    far = none.copy()
    far[-1] = 1e6  # a stop, never nearer than a leader or NO_LEADER_GAP_M
    args = (observation, vids, rows, lanes, st, leaders, shapes)
    got = observe_rows(LaneTable(sec), *args, none, stop_gap_m=stop_gap_m)
    want = observe_rows(LaneTable(sec), *args, far, stop_gap_m=stop_gap_m)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.tobytes() == w.tobytes()
    # The deficit (own minGap 3.0 - 2.0) is taken off where there is a leader: not v0
    # (none) nor v7 (its truck is off the road).
    plain = observe_rows(LaneTable(sec), *args, none)[0][:, LEADER_COLUMN]
    deficit = np.array([0.0] + [1.0] * 6 + [0.0]) * (stop_gap_m is not None)
    np.testing.assert_array_equal(plain - got[0][:, LEADER_COLUMN], deficit)

"""``deploy.observe.observe_rows`` keeps per-run tables and a buffer in its ``LaneTable``
(the lanes' own observation columns, the driven vehicles' index by state row): a table
reused over steps of different sizes gives bit for bit what a fresh one gives, and the
buffer holds no index of an earlier step."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "road"))

from test_section_leaders import EDGES, build_merge_net  # noqa: E402

from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table, observe_rows, states_of  # noqa: E402
from macromicro_sumo.road.section import read_section  # noqa: E402


def _step(k: int) -> tuple:
    """A step with ``k`` vehicles on a_0 / a_1 (the first ``k - 1`` driven), each led by the
    next one on its lane at a 12 m gap, the last by an undriven truck off the road; one
    vehicle's lane ends 3 m ahead (a standing leader)."""
    states = {f"v{i}": (f"a_{i % 2}", 20.0 + 15.0 * i, 10.0 + i, 0.0) for i in range(k)}
    st = states_of(states)
    vids = [f"v{i}" for i in range(k - 1)]
    rows = np.array([st.index[v] for v in vids])
    leaders = [(f"v{i + 2}" if i + 2 < k else "truck", 12.0) for i in range(k - 1)]
    leaders[0] = ("", -1.0)
    stop = np.full(k - 1, np.inf)
    stop[-1] = 3.0
    return vids, rows, [st.lanes[r] for r in rows], st, leaders, stop


@pytest.mark.parametrize("observation", ["lookahead_gap", "lookahead"])
def test_a_reused_lane_table_gives_a_fresh_ones_results(tmp_path: Path, observation) -> None:
    sec = read_section(build_merge_net(tmp_path, (20.0, 25.0, 30.0)), EDGES, closed=False)
    shapes = Table.of_rows({**{f"v{i}": (5.0, 2.5, 4.5) for i in range(9)},
                            "truck": (12.0, 2.5, 4.0)}, STANDING)  # fmt: skip
    reused = LaneTable(sec)
    for k in (4, 9, 3, 9):  # the buffer grows, then serves a smaller step
        vids, rows, lanes, st, leaders, stop = _step(k)
        got = observe_rows(reused, observation, vids, rows, lanes, st, leaders, shapes, stop)
        want = observe_rows(
            LaneTable(sec), observation, vids, rows, lanes, st, leaders, shapes, stop
        )
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype and g.tobytes() == w.tobytes()
        obs, _, _, lead_index = got
        assert obs.flags.c_contiguous
        # v_i is led by v_{i+2}, driven where i + 2 < k - 1; v0 has no leader, the last a
        # standing one at its lane's end: -1.
        expect = [i + 2 if i > 0 and i + 2 < k - 1 else -1 for i in range(k - 1)]
        assert lead_index.tolist() == expect
        assert np.all(reused.driven_rows(0) == -1)
        np.testing.assert_array_equal(obs[:, 1], reused.limit_mps[reused.codes(lanes)])
        assert np.all(obs[:, 0] == st.speed_mps[rows])

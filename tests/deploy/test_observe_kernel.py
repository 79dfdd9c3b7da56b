"""``deploy.observe.observe_rows`` with road/kernels.c's leader columns gives numpy's
observations, gaps, decels and leader indices to the bit: leaders driven, undriven, off
the road and none, a standing leader nearer (a lane's end) or not, each layout, with the
prior's stop gap, and steps that grow and shrink the driven buffer."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "road"))

from test_section_leaders import EDGES, build_merge_net  # noqa: E402

from macromicro_sumo.deploy import observe  # noqa: E402
from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table, states_of  # noqa: E402
from macromicro_sumo.road.section import read_section  # noqa: E402

kernels = pytest.importorskip(
    "macromicro_sumo.road.kernels", reason="road/kernels.c not built (no C compiler)"
)


def _step(k: int, rng: np.random.Generator, stop_ahead: bool) -> tuple:
    states = {
        f"v{i}": (f"a_{i % 2}", 20.0 + 15.0 * i, float(rng.uniform(0, 30)), 0.0) for i in range(k)
    }
    st = states_of(states)
    vids = [f"v{i}" for i in range(k - 1)]
    rows = np.array([st.index[v] for v in vids])
    pick = ("", "truck", "ghost") + tuple(f"v{i}" for i in range(k))
    leaders = []
    for _ in vids:
        lead = pick[int(rng.integers(len(pick)))]
        leaders.append((lead, -1.0) if lead == "" else (lead, float(rng.uniform(-1, 1200))))
    stop = np.full(k - 1, np.inf)
    if stop_ahead:
        stop[rng.random(k - 1) < 0.4] = float(rng.uniform(0, 40))
    return vids, rows, [st.lanes[r] for r in rows], st, leaders, stop


@pytest.mark.parametrize("observation", ["lookahead_gap", "lookahead", "paper"])
def test_the_same_results_to_the_bit(tmp_path: Path, observation: str) -> None:
    assert observe.kernels is kernels
    sec = read_section(build_merge_net(tmp_path, (20.0, 25.0, 30.0)), EDGES, closed=False)
    shapes = Table.of_rows(
        {
            **{f"v{i}": (5.0 + i % 3, 2.0 + i % 2, 4.5) for i in range(40)},
            "truck": (12.0, 2.5, 4.0),
        },
        STANDING,
    )
    rng = np.random.default_rng(11)
    on, off = LaneTable(sec), LaneTable(sec)
    for trial, k in enumerate((4, 30, 3, 40, 2, 25, 12)):
        for stop_ahead in (False, True):
            for stop_gap in (None, 2.2):
                vids, rows, lanes, st, leaders, stop = _step(k, rng, stop_ahead)
                args = (observation, vids, rows, lanes, st, leaders, shapes, stop)
                got = observe.observe_rows(on, *args, stop_gap_m=stop_gap)
                observe.kernels = None
                try:
                    want = observe.observe_rows(off, *args, stop_gap_m=stop_gap)
                finally:
                    observe.kernels = kernels
                for g, w in zip(got, want, strict=True):
                    assert g.dtype == w.dtype and g.shape == w.shape
                    assert g.tobytes() == w.tobytes(), (trial, stop_ahead, stop_gap)
                assert np.all(on.driven_rows(0) == -1)  # the buffer left as found


def test_other_forms_left_to_numpy() -> None:
    """A non-contiguous or float32 operand, an index out of range: False, nothing written."""
    n, rows = 3, np.array([0, 1, 2])
    gap, lead_row, shape = np.array([5.0, 6.0, 7.0]), np.array([1, -1, 0]), np.zeros(6, np.int64)
    speed, col, driven = np.ones(3), np.ones(2), np.full(7, -1, np.int64)
    cols, index, ok = np.full((7, n), 9.0), np.full(n, 9, np.int64), np.zeros(n, bool)
    good = (gap, lead_row, rows, shape, speed, col, col, col, driven, 1000.0, 9.0, cols, index, ok)
    assert kernels.leader_columns(*good) is True
    for i, bad in (
        (0, gap.astype(np.float32)),
        (4, np.ones(6)[::2]),
        (1, np.array([1, -1, 3])),  # a leader row past the speeds
        (3, np.array([0, 0, 0, 0, 0, 2])),  # a shape code past the table
        (8, np.full(3, -1, np.int64)),  # a buffer not longer than the speeds
    ):
        args = list(good)
        args[i] = bad
        cols[:], index[:] = 9.0, 9
        assert kernels.leader_columns(*args) is False
        assert (cols == 9.0).all() and (index == 9).all()

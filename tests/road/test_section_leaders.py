"""Leaders along the network's lane connections (``road.leaders.section_leaders``).

A tiny merge built with netconvert: a 2-lane road gains an on-ramp lane on the right, so
the through lanes' indices shift by one at the boundary; the lanes then drop back to two.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import NETS, netconvert

from macromicro_sumo.road.leaders import lane_leaders, section_leaders
from macromicro_sumo.road.section import NO_LEADER_GAP_M, STOP, Section, read_section
from macromicro_sumo.truth.section_macro import trajectory_macro

EDGES = ["a", "b", "c"]


def build_merge_net(folder: Path, b_limits_mps: tuple[float, ...] = ()) -> Path:
    """a (2 lanes, 300 m) -> b (3 lanes: the ramp ``r`` joins on the right, 300 m) -> c (2
    lanes, 300 m): a_0 -> b_1, a_1 -> b_2, r_0 -> b_0, b_0 ends, b_1 -> c_0, b_2 -> c_1.
    ``b_limits_mps``: b's lanes' own speed limits, right to left (default: the edge's 30)."""
    b_lanes = "".join(f'<lane index="{i}" speed="{v}"/>' for i, v in enumerate(b_limits_mps))
    return netconvert(
        folder,
        '<node id="n0" x="0" y="0"/><node id="n1" x="300" y="0"/>'
        '<node id="n2" x="600" y="0"/><node id="n3" x="900" y="0"/>'
        '<node id="r0" x="0" y="-60"/>',
        '<edge id="a" from="n0" to="n1" numLanes="2" speed="30"/>'
        '<edge id="r" from="r0" to="n1" numLanes="1" speed="25"/>'
        f'<edge id="b" from="n1" to="n2" numLanes="3" speed="30">{b_lanes}</edge>'
        '<edge id="c" from="n2" to="n3" numLanes="2" speed="30"/>',
        '<connection from="a" to="b" fromLane="0" toLane="1"/>'
        '<connection from="a" to="b" fromLane="1" toLane="2"/>'
        '<connection from="r" to="b" fromLane="0" toLane="0"/>'
        '<connection from="b" to="c" fromLane="1" toLane="0"/>'
        '<connection from="b" to="c" fromLane="2" toLane="1"/>',
        name="merge",
    )


@pytest.fixture(scope="module")
def merge(tmp_path_factory) -> Section:
    net = build_merge_net(tmp_path_factory.mktemp("merge"))
    return read_section(net, EDGES, closed=False)


def test_connections_are_read(merge):
    assert merge.links[0, 0, 1] and merge.links[0, 1, 2] and not merge.links[0, 0, 0]
    assert merge.links[1, 1, 0] and merge.links[1, 2, 1] and not merge.links[1, 0].any()
    assert merge.lane_ends[1, 0] and not merge.lane_ends[0].any()
    assert not merge.lane_ends[2].any()  # the open end is not a lane end
    again = Section.from_json(merge.to_json())
    np.testing.assert_array_equal(again.links, merge.links)
    np.testing.assert_array_equal(again.lane_ends, merge.lane_ends)


def test_leader_across_a_lane_added_on_the_right(merge):
    """A vehicle on a's right lane follows the vehicle on b's lane 1 (the lane it continues
    onto), not the one on b's lane 0 (the ramp lane), which lane indices would give."""
    b0 = merge.offsets_m[1]
    lane = np.array([0, 0, 1, 1])
    arc = np.array([b0 - 30.0, b0 + 10.0, b0 + 40.0, b0 - 5.0])
    leader, spacing = section_leaders(merge, lane, arc)
    assert leader[0] == 2 and spacing[0] == pytest.approx(70.0)
    # ... whereas lane indices pick the ramp-lane vehicle 40 m closer:
    assert lane_leaders(lane, arc, merge.length_m, False)[0][0] == 1
    # a's left lane (index 1) continues onto b's lane 2: nothing there.
    assert leader[3] == -1 and spacing[3] == NO_LEADER_GAP_M
    # the ramp lane ends: its driver sees a standing obstacle at the lane's end.
    assert leader[1] == STOP
    assert spacing[1] == pytest.approx(merge.lengths_m[1] - 10.0)


def test_leader_through_an_empty_edge_and_a_junction(merge):
    """Leaders are found two edges ahead, along the connections (b_2 -> c_1), and a vehicle
    inside a junction counts on the lane it enters."""
    c0 = merge.offsets_m[2]
    lane = np.array([1, 1, 0])
    in_junction = merge.offsets_m[1] + merge.lengths_m[1] + 0.5 * merge.junction_m[1]
    arc = np.array([20.0, c0 + 50.0, in_junction])
    leader, spacing = section_leaders(merge, lane, arc)
    assert leader[0] == 1 and spacing[0] == pytest.approx(c0 + 30.0)
    # the vehicle in the junction b -> c on lane index 0 (c_0) has nothing ahead on c_0
    assert leader[2] == -1
    # a red light's stop line is a standing leader
    leader, spacing = section_leaders(merge, lane, arc, np.array([1]), np.array([c0 + 20.0]))
    assert leader[0] == STOP and spacing[0] == pytest.approx(c0)
    assert leader[1] == -1


def test_loop_matches_lane_leaders():
    ring = read_section(
        Path(__file__).resolve().parents[2] / "sumo_nets" / "ring_r100_e4.net.xml",
        ["e0", "e1", "e2", "e3"],
        True,
    )
    rng = np.random.default_rng(0)
    arc = np.sort(rng.uniform(0, ring.length_m, 12))
    lane = np.zeros(12, dtype=np.int64)
    got = section_leaders(ring, lane, arc)
    want = lane_leaders(lane, arc, ring.length_m, True)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_allclose(got[1], want[1])
    alone = section_leaders(ring, lane[:1], arc[:1])
    assert alone[0][0] == 0 and alone[1][0] == pytest.approx(ring.length_m)


def test_truth_macro_spacings_follow_the_connections(merge):
    """macro.csv's spacing dispersion (trajectory source) uses the environment's leaders:
    at the ramp merge the spacings are 70 and 60 m (std 5), where lane indices would pair
    the through lane with the ramp lane (40, 45, 60 m)."""
    b0 = merge.offsets_m[1]
    traj = pd.DataFrame(
        {
            "run": 0,
            "time_s": 0.0,
            "lane_index": [0, 0, 1, 1, 1],
            "arc_m": [b0 - 30.0, b0 + 10.0, b0 + 40.0, b0 - 5.0, b0 + 100.0],
            "speed_mps": 20.0,
        }
    )
    row = trajectory_macro(traj, merge, 1.0, 0.0, 1.0).iloc[0]
    assert row["std_spacing_m"] == pytest.approx(5.0)


def test_a_closed_one_lane_loop_finds_the_next_item_round_it() -> None:
    """The ring's shortcut (``loop_successors``): every vehicle's leader is the nearest item
    ahead round the loop (a red light's stop line: STOP), equal positions in index order, a
    lone vehicle its own leader a lap ahead; checked by brute force on drawn positions."""
    section = read_section(NETS / "ring_r100_e4.net.xml", ["e0", "e1", "e2", "e3"], True)
    length = section.length_m
    rng = np.random.default_rng(5)
    for trial in range(300):
        n, k = int(rng.integers(1, 25)), int(rng.integers(0, 3))
        arc = rng.uniform(-5.0, length + 5.0, n)  # the loop wraps either way
        if trial % 3 == 0 and n > 1:
            arc[1] = arc[0]
        stops = rng.uniform(0.0, length, k)
        leader, spacing = section_leaders(
            section, np.zeros(n, dtype=np.int64), arc, np.zeros(k, dtype=np.int64), stops
        )
        s = np.mod(np.concatenate([arc, stops]), length)
        ahead = np.mod(s[None, :] - s[:, None], length)
        index = np.arange(len(s))
        ahead[(ahead == 0) & (index[None, :] <= index[:, None])] = length  # behind, or itself
        want = ahead[:n].argmin(axis=1)
        np.testing.assert_array_equal(leader, np.where(want >= n, STOP, want))
        np.testing.assert_allclose(spacing, ahead[:n].min(axis=1), atol=1e-9)

"""A vehicle standing across a red line in the one leader search (``road.leaders.
section_ahead`` with the vehicles' lengths): the stop points are ordered against the tails
of the vehicles past them, in the same sort, where stop 48's fix (c141e41) searched the
vehicles' leaders a second time without the stop points and compared the two. Random scenes
crowded round the lines on four nets (a merge whose through lanes shift by one, SUMO's
game/cross with its turning lanes, a one-lane ring's fast path, two lines 4 m apart) give
the second search's leaders, and its spacings to the bit on the open walk.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sumo
from conftest import NETS, netconvert
from test_section_leaders import EDGES, build_merge_net

from macromicro_sumo.road.leaders import (
    AHEAD_RED,
    AHEAD_VEHICLE,
    section_ahead,
    standing_spacing_m,
)
from macromicro_sumo.road.section import Section, read_section

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


def two_searches(
    section: Section,
    lane: np.ndarray,
    arc: np.ndarray,
    stop_lane: np.ndarray,
    stop_arc: np.ndarray,
    on_route: np.ndarray,
    length: np.ndarray,
    min_gap: np.ndarray,
    stop_gap: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Stop 48's leaders and spacings (c141e41's ``_across_the_line``): the search with the
    stop points, then without, the vehicle taken where the line is not nearer."""
    lead, gap, kind = section_ahead(section, lane, arc, stop_lane, stop_arc, on_route)
    veh, veh_gap, _ = section_ahead(section, lane, arc, None, None, on_route)
    car = (kind == AHEAD_RED) & (veh >= 0)
    standing = standing_spacing_m(gap, length, stop_gap, min_gap)
    take = car & ~(standing + length[np.maximum(veh, 0)] - length < veh_gap)
    return np.where(take, veh, lead), np.where(take, veh_gap, gap)


def crowd(
    section: Section, lines: list[tuple[int, int]], n: int, rng: np.random.Generator
) -> tuple[np.ndarray, ...]:
    """``n`` vehicles, most within 15 m of the ends of the edges of ``lines`` ((edge,
    lane) of each red line), on random lanes, with random lengths (4-16 m), minGaps and
    jmStoplineGaps, a random half on the section's route; the stop points at the lines."""
    ends = section.offsets_m + section.lengths_m
    at = rng.integers(0, len(lines), n)
    edge = np.array([lines[i][0] for i in at])
    arc = ends[edge] + rng.uniform(-15.0, 15.0, n)
    far = rng.random(n) < 0.2
    arc[far] = rng.uniform(0.0, section.length_m, far.sum())
    e = section.edge_index(section.wrap(arc))
    lane = rng.integers(0, section.n_lanes[e])
    stop_lane = np.array([ln for _, ln in lines])
    stop_arc = np.round(np.array([ends[e] for e, _ in lines]), 6)
    return (
        lane,
        section.wrap(arc),
        stop_lane,
        stop_arc,
        rng.random(n) < 0.5,
        rng.uniform(4.0, 16.0, n),
        rng.uniform(1.0, 3.0, n),
        rng.uniform(-0.5, 2.0, n),  # a negative jmStoplineGap too: SUMO reads it
    )


@pytest.fixture(scope="module")
def nets(tmp_path_factory) -> dict[str, tuple[Section, list[tuple[int, int]]]]:
    """Each net's section and its red lines ((edge, lane) whose end is the line)."""
    merge = read_section(build_merge_net(tmp_path_factory.mktemp("merge")), EDGES, False)
    cross = read_section(CROSS, ["1fi", "1si", "2o", "2fo"], closed=False)
    ring = read_section(NETS / "ring_r100_e4.net.xml", ["e0", "e1", "e2", "e3"], True)
    short = netconvert(
        tmp_path_factory.mktemp("short"),
        '<node id="n0" x="0" y="0"/><node id="n1" x="100" y="0"/>'
        '<node id="n2" x="104" y="0"/><node id="n3" x="204" y="0"/>',
        '<edge id="a" from="n0" to="n1" numLanes="1"/>'
        '<edge id="b" from="n1" to="n2" numLanes="1"/>'
        '<edge id="c" from="n2" to="n3" numLanes="1"/>',
        "",
        name="short",
    )
    return {
        "merge": (merge, [(0, 0), (0, 1), (1, 1), (1, 2)]),
        "cross": (cross, [(1, 0), (1, 1), (1, 2)]),
        "ring": (ring, [(0, 0), (2, 0)]),
        "short": (read_section(short, ["a", "b", "c"], False), [(0, 0), (1, 0)]),
    }


@pytest.mark.parametrize("net", ["merge", "cross", "ring", "short"])
def test_one_search_finds_the_second_searchs_leaders(nets, net: str) -> None:
    """200 crowded scenes: the leaders of one search with the lengths are those of two
    searches; the spacings are equal to the bit on the open walk (a loop's sums of arcs may
    differ in the last bit); every scene that has a straddling leader counts."""
    section, lines = nets[net]
    rng = np.random.default_rng(49)
    taken = 0
    for _ in range(200):
        lane, arc, sl, sa, route, length, min_gap, stop_gap = crowd(section, lines, 30, rng)
        want_lead, want_gap = two_searches(
            section, lane, arc, sl, sa, route, length, min_gap, stop_gap
        )
        lead, gap, kind = section_ahead(
            section, lane, arc, sl, sa, route, length, min_gap, stop_gap
        )
        np.testing.assert_array_equal(lead, want_lead)
        if section.closed:
            np.testing.assert_allclose(gap, want_gap, rtol=0, atol=1e-9)
        else:
            np.testing.assert_array_equal(gap, want_gap)
        first, _, first_kind = section_ahead(section, lane, arc, sl, sa, route)
        moved = first_kind == AHEAD_RED
        moved &= lead >= 0
        assert (kind[moved] == AHEAD_VEHICLE).all()
        taken += int(moved.sum())
    assert taken >= 20  # the scenes do put vehicles across the lines


def test_two_lines_within_a_trucks_length(nets) -> None:
    """A 14 m truck whose front is 3 m past b's end, its tail 7 m before a's end (b is 4 m
    long and the junctions of the straight net have no length): both lines lie within it; the car 20 m
    before a's line follows the truck through both stop points (spacing 20 + 4 + 3 + the
    junctions), as the second search found it; 20 m past the lines, the line is nearer."""
    section, _ = nets["short"]
    ends = section.offsets_m + section.lengths_m
    stop_arc = np.round(ends[:2], 6)
    for past_m, leads in ((3.0, True), (20.0 + 14.0, False)):
        arc = np.array([ends[0] - 20.0, ends[1] + past_m])
        length = np.array([5.0, 14.0])
        lead, gap, kind = section_ahead(
            section, np.zeros(2, np.int64), arc, np.zeros(2, np.int64), stop_arc, None, length
        )
        if leads:
            assert lead[0] == 1 and kind[0] == AHEAD_VEHICLE
            assert gap[0] == pytest.approx(arc[1] - arc[0])
        else:
            assert kind[0] == AHEAD_RED and gap[0] == pytest.approx(20.0)


def test_without_lengths_or_stop_points_nothing_moves(nets) -> None:
    """Without the lengths the search is stop 48's first (a line hides the vehicle across
    it); with the lengths and no stop points, the search is the one without them, to the bit."""
    section, lines = nets["cross"]
    lane, arc, sl, sa, route, length, min_gap, stop_gap = crowd(
        section, lines, 30, np.random.default_rng(7)
    )
    plain = section_ahead(section, lane, arc, None, None, route)
    with_len = section_ahead(section, lane, arc, None, None, route, length, min_gap, stop_gap)
    for a, b in zip(plain, with_len, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(("stopline_gap_m", "leads"), [(-1.0, True), (1.0, False), (0.0, False)])
def test_a_negative_stopline_gap_reaches_further(nets, stopline_gap_m: float, leads: bool) -> None:
    """A 5 m car whose tail is 3 m past a's red line; its follower 20 m before the line,
    minGap 2.5 m: SUMO's gap to the car is 20 + 3 - 2.5 = 20.5 m, to the line 20 -
    jmStoplineGap. A jmStoplineGap of -1 m (the driver stops 1 m past the line) makes the
    car nearer (21 m to the line), 1 m or 0 leaves the line nearer: the search's early test
    (only a tail less than minGap - min(jmStoplineGap, 0) past the line) keeps the first."""
    section, _ = nets["short"]
    ends = section.offsets_m + section.lengths_m
    arc = np.array([ends[0] - 20.0, ends[0] + 8.0])
    zero = np.zeros(2, np.int64)
    lead, gap, kind = section_ahead(
        section,
        zero,
        arc,
        zero[:1],
        np.round(ends[:1], 6),
        None,
        np.array([5.0, 5.0]),
        np.array([2.5, 2.5]),
        np.array([stopline_gap_m, 1.0]),
    )
    if leads:
        assert lead[0] == 1 and kind[0] == AHEAD_VEHICLE and gap[0] == pytest.approx(28.0)
    else:
        assert kind[0] == AHEAD_RED and gap[0] == pytest.approx(20.0)

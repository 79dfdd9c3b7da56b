"""Stage I's gaps follow the network's lane connections (issue 17; ``section_lanes``).

Two small nets built by netconvert, each a section A -> B:
- ``index_change``: A has two lanes, B one; A's lane 1 continues onto B's lane 0 (A's
  lane 0 ends). The through lane changes index at the junction (drawn net 501);
- ``lane_added``: A has one lane, B two; an on-ramp R adds B's lane 0 on the right, so
  A's lane 0 continues onto B's lane 1 (every on-ramp merge of the drawn nets, Bremen);
- ``fan_out``: A's one lane continues onto both of B's (drawn 501's last junction,
  game/cross's approach).
Gaps per SUMO lane index did not see a vehicle at A's end and one at B's start as
neighbours: the generator put cars a metre apart across the junction, or a fast car just
behind a slow one, and ``drop_unsafe_pairs`` dropped them afterwards.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import netconvert

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.generator.section_lanes import through_lanes
from macromicro_sumo.generator.section_model import SectionGeneratorNet
from macromicro_sumo.generator.section_sampler import complete_section
from macromicro_sumo.generator.section_scene import Road, scene_gaps
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.section import Section, read_section

S_MIN = 7.5  # psi's smallest front-to-front spacing [m]: a 5 m car and 2.5 m of gap
BRAKE = 4.5
STEP = 0.5


def build(folder: Path, kind: str) -> Section:
    nodes = [
        '<node id="n0" x="0" y="0"/>',
        '<node id="n1" x="400" y="0"/>',
        '<node id="n2" x="800" y="0"/>',
    ]
    if kind == "fan_out":
        edges = [
            '<edge id="A" from="n0" to="n1" numLanes="1" speed="20"/>',
            '<edge id="B" from="n1" to="n2" numLanes="2" speed="20"/>',
        ]
        cons = [
            '<connection from="A" to="B" fromLane="0" toLane="0"/>',
            '<connection from="A" to="B" fromLane="0" toLane="1"/>',
        ]
    elif kind == "index_change":
        edges = [
            '<edge id="A" from="n0" to="n1" numLanes="2" speed="20"/>',
            '<edge id="B" from="n1" to="n2" numLanes="1" speed="20"/>',
        ]
        cons = ['<connection from="A" to="B" fromLane="1" toLane="0"/>']
    else:
        nodes.append('<node id="r0" x="200" y="-40"/>')
        edges = [
            '<edge id="A" from="n0" to="n1" numLanes="1" speed="20"/>',
            '<edge id="R" from="r0" to="n1" numLanes="1" speed="20"/>',
            '<edge id="B" from="n1" to="n2" numLanes="2" speed="20"/>',
        ]
        cons = [
            '<connection from="A" to="B" fromLane="0" toLane="1"/>',
            '<connection from="R" to="B" fromLane="0" toLane="0"/>',
        ]
    folder.mkdir(parents=True, exist_ok=True)
    net = netconvert(folder, "\n".join(nodes), "\n".join(edges), "\n".join(cons), name=kind)
    return read_section(net, ["A", "B"], False)


@pytest.fixture(scope="module", params=["index_change", "lane_added"])
def net(request, tmp_path_factory) -> tuple[str, Section]:
    kind = request.param
    return kind, build(tmp_path_factory.mktemp(kind), kind)


def through(kind: str) -> tuple[int, int]:
    """SUMO lane indices of the through lane on A and on B."""
    return (1, 0) if kind == "index_change" else (0, 1)


def scenes(sec: Section, kind: str, n: int) -> SectionSnapshots:
    """``n`` scenes with two observed cars on the through lane: one 30 m before A's end at
    16 m/s, one 20 m into B at 1 m/s (a queue's tail); 4 vehicles to hide."""
    on_a, on_b = through(kind)
    end_a = float(sec.offsets_m[0] + sec.lengths_m[0])
    psi = np.tile([10.0, 40.0, np.nan, 1.0, 16.0, S_MIN, np.inf, S_MIN], (n, 1))
    return SectionSnapshots(
        run=np.zeros(n, dtype=int),
        time_s=np.arange(n) * 10.0,
        lane=np.tile([on_a, on_b], (n, 1)),
        arc_m=np.tile([end_a - 30.0, float(sec.offsets_m[1]) + 20.0], (n, 1)),
        speed_mps=np.tile([16.0, 1.0], (n, 1)),
        length_m=np.full((n, 2), 5.0),
        valid=np.ones((n, 2), dtype=bool),
        observed=np.ones((n, 2), dtype=bool),
        psi=psi,
        k_true=np.full(n, 4),
        k_est=np.full(n, 4),
    )


def test_a_gaps_leader_is_the_next_vehicle_along_the_connections(net) -> None:
    """The gap ahead of the car before the junction ends at the car after it, as
    ``section_leaders`` (the envs' leader search) pairs them: its length is their
    spacing, its leader's speed the second car's. Per SUMO lane index it ran on to the open
    end with no leader (the two cars are on different indices)."""
    kind, sec = net
    snaps = scenes(sec, kind, 1)
    road = Road.of(sec)
    lead, spacing = section_leaders(sec, snaps.lane[0], snaps.arc_m[0])
    assert lead.tolist() == [1, -1]
    lane = torch.as_tensor(road.lane_numbers(snaps.lane, snaps.arc_m))
    assert lane[0, 0] == lane[0, 1]  # one lane along the connections
    g = scene_gaps(
        lane,
        torch.as_tensor(snaps.arc_m),
        torch.as_tensor(snaps.speed_mps),
        torch.ones(1, 2, dtype=torch.bool),
        road,
        torch.tensor([S_MIN]),
        None,
    )
    at = int(np.flatnonzero(np.isclose(g.start[0, :2].numpy(), snaps.arc_m[0, 0]))[0])
    assert bool(g.has_l[0, at])
    assert float(g.length[0, at]) == pytest.approx(spacing[0])
    assert float(g.v_l[0, at]) == 1.0


def test_no_generated_vehicle_is_placed_where_it_must_be_dropped(net) -> None:
    """Generated vehicles (an untrained generator: anywhere, any speed in psi's range, with
    the scenario's braking bound) keep psi's minimum spacing to their leader along the
    connections, and every follower can stop behind its leader: none is dropped. Per
    SUMO lane index, vehicles between the first car and A's end had no leader and were
    given speeds they could not stop from behind the standing car across the junction."""
    kind, sec = net
    n = 32
    snaps = scenes(sec, kind, n)
    torch.manual_seed(0)
    gen = SectionGeneratorNet(32)
    comp = complete_section(gen, sec, snaps, snaps.k_true, 20, 1, BRAKE, STEP)
    assert int(comp.dropped.sum()) == 0
    assert (comp.generated.sum(axis=1) == 4).all()
    bt = BRAKE * STEP
    near = 0
    for s in range(n):
        on = np.flatnonzero(comp.valid[s])
        lane, arc, v = comp.lane[s, on], comp.arc_m[s, on], comp.speed_mps[s, on]
        lead, spacing = section_leaders(sec, lane, arc)
        gen_s = comp.generated[s, on]
        for f in np.flatnonzero(lead >= 0):
            j = lead[f]
            if not (gen_s[f] or gen_s[j]):
                continue
            assert spacing[f] >= S_MIN - 1e-6, (s, f, spacing[f])
            room = 2.0 * BRAKE * (spacing[f] - S_MIN)
            assert v[f] ** 2 + 2 * bt * v[f] <= v[j] ** 2 + room + 1e-6, (s, f)
            near += bool(abs(arc[f] - sec.offsets_m[1]) < 60.0)
    assert near > 5  # generated pairs near the junction were checked


def test_a_lane_a_fan_out_begins_follows_the_feeding_lanes_last_vehicle(tmp_path) -> None:
    """A's lane fans out onto B's two: the generator goes on along B's lane 0 and numbers
    B's lane 1 anew. The envs' leader search takes the nearest of the continuations, so a
    vehicle at the start of B's lane 1 leads the last car on A: the head gap of that lane
    starts at that car, with its speed (it began at the section's start, with no
    follower, and an untrained generator's vehicles there were dropped)."""
    sec = build(tmp_path, "fan_out")
    road = Road.of(sec)
    end_a = float(sec.offsets_m[0] + sec.lengths_m[0])
    arc = np.array([[end_a - 30.0]])
    assert road.lane_numbers(np.array([0, 1]), np.full(2, sec.offsets_m[1] + 1.0)).tolist() == [
        0,
        1,
    ]
    g = scene_gaps(
        torch.zeros(1, 1, dtype=torch.int64),
        torch.as_tensor(arc),
        torch.tensor([[16.0]], dtype=torch.float64),
        torch.ones(1, 1, dtype=torch.bool),
        road,
        torch.tensor([S_MIN]),
        None,
    )
    head = 1 + 1  # one vehicle slot, then one head gap per lane: lane 1's
    assert bool(g.has_f[0, head]) and float(g.v_f[0, head]) == 16.0
    assert float(g.start[0, head]) == pytest.approx(end_a - 30.0)
    assert not bool(g.has_f[0, 1])  # lane 0's head gap: upstream of the car, on A
    n = 32
    snaps = SectionSnapshots(
        run=np.zeros(n, dtype=int),
        time_s=np.arange(n) * 10.0,
        lane=np.zeros((n, 1), dtype=np.int64),
        arc_m=np.full((n, 1), end_a - 30.0),
        speed_mps=np.full((n, 1), 16.0),
        length_m=np.full((n, 1), 5.0),
        valid=np.ones((n, 1), dtype=bool),
        observed=np.ones((n, 1), dtype=bool),
        psi=np.tile([10.0, 40.0, np.nan, 1.0, 16.0, S_MIN, np.inf, S_MIN], (n, 1)),
        k_true=np.full(n, 4),
        k_est=np.full(n, 4),
    )
    torch.manual_seed(0)
    comp = complete_section(SectionGeneratorNet(32), sec, snaps, snaps.k_true, 20, 1, BRAKE, STEP)
    assert int(comp.dropped.sum()) == 0


def test_a_fan_out_continues_onto_the_lane_that_reaches_the_sections_end(tmp_path) -> None:
    """A's lane fans out onto B's two; B's lane 0 goes on only onto C's lane 0, which ends
    (netgen_corridor's e3 -> e4 -> e5), B's lane 1 through C's lane 1 onto D. The
    generator's number of A's lane goes on along B's lane 1 (it went onto lane 0, the
    nearest index, and the corridor's through traffic changed number at B)."""
    nodes = "\n".join(f'<node id="n{i}" x="{300 * i}" y="0"/>' for i in range(5))
    edges = "\n".join(
        f'<edge id="{e}" from="n{i}" to="n{i + 1}" numLanes="{k}" speed="20"/>'
        for i, (e, k) in enumerate([("A", 1), ("B", 2), ("C", 2), ("D", 1)])
    )
    cons = "\n".join(
        f'<connection from="{a}" to="{b}" fromLane="{i}" toLane="{j}"/>'
        for a, b, i, j in [("A", "B", 0, 0), ("A", "B", 0, 1), ("B", "C", 0, 0),
                           ("B", "C", 1, 1), ("C", "D", 1, 0)]
    )  # fmt: skip
    sec = read_section(netconvert(tmp_path, nodes, edges, cons), ["A", "B", "C", "D"], False)
    number, _ = through_lanes(sec)
    assert number[:, 0].tolist() == [0, 1, 1, 0]  # SUMO lane 0 of each edge
    assert number[1:3, 1].tolist() == [0, 0]  # B's and C's lane 1 go on from A


def test_the_generator_trains_on_sumo_lane_indices(net) -> None:
    """Training (``section_train``) reads the road on SUMO's lane indices, with no fan-out
    followers: the gaps it trained on before the numbering (its weights are 3e1f4d0's bit
    for bit), while ``complete_section`` completes along the connections."""
    kind, sec = net
    plain = Road.of(sec, connections=False)
    lanes, arcs = np.array([0, 1, 0, 1]), np.array([10.0, 10.0, 500.0, 500.0])
    exists = lanes < sec.n_lanes[sec.edge_index(arcs)]
    assert plain.lane_numbers(lanes, arcs)[exists].tolist() == lanes[exists].tolist()
    assert (plain.feeder < 0).all()
    assert Road.of(sec).lane_numbers(lanes, arcs)[exists].tolist() != lanes[exists].tolist()

"""Random corridors: deterministic per seed, connected, with demand that fits the network."""

from __future__ import annotations

from pathlib import Path

from macromicro_sumo.sumo.demand import check_demand
from macromicro_sumo.sumo.inputs import read_net, resolve_inputs
from macromicro_sumo.sumo.netgen import LANES_RANGE, SPEED_RANGE_MPS, random_corridor


def test_same_seed_same_bytes(tmp_path: Path) -> None:
    a = random_corridor(tmp_path / "a", seed=5)
    b = random_corridor(tmp_path / "b", seed=5)
    c = random_corridor(tmp_path / "c", seed=6)
    assert a.net_file.read_bytes() == b.net_file.read_bytes()
    assert a.routes_file.read_bytes() == b.routes_file.read_bytes()
    assert (a.section_edges, a.lanes_per_edge, a.lengths_m) == (
        b.section_edges,
        b.lanes_per_edge,
        b.lengths_m,
    )
    assert (a.lanes_per_edge, a.lengths_m, a.speeds_mps) != (
        c.lanes_per_edge,
        c.lengths_m,
        c.speeds_mps,
    )


def test_section_is_connected_and_matches_the_net(tmp_path: Path) -> None:
    c = random_corridor(tmp_path, seed=3, n_edges=6)
    net = read_net(c.net_file)
    edges = [net.getEdge(e) for e in c.section_edges]
    assert len(edges) == 6
    for up, down in zip(edges, edges[1:], strict=False):
        assert down in up.getOutgoing(), (up.getID(), down.getID())
    assert not edges[-1].getOutgoing() and not edges[0].getIncoming()  # one way, open ends
    assert [e.getLaneNumber() for e in edges] == list(c.lanes_per_edge)
    assert all(LANES_RANGE[0] <= k <= LANES_RANGE[1] for k in c.lanes_per_edge)
    assert all(SPEED_RANGE_MPS[0] <= e.getSpeed() <= SPEED_RANGE_MPS[1] for e in edges)
    assert [round(e.getLength(), 3) for e in edges] == list(c.lengths_m)


def test_demand_fits_and_has_both_models(tmp_path: Path) -> None:
    c = random_corridor(tmp_path, seed=11)
    inputs = resolve_inputs(c.sumocfg, None, [], [], "test")
    vtypes = check_demand(inputs, read_net(inputs.net_file))
    assert {v.car_follow_model for v in vtypes.values()} == {"IDM", "Krauss"}
    assert all(v.length_m > 0 for v in vtypes.values())

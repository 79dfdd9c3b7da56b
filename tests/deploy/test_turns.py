"""``deploy.turns``: driven vehicles whose route turns off the section at a junction of it
(``deploy.turns.Turns``), on a real network through libsumo.

U (100 m) -> A (300 m, one lane, 15 m/s) -> junction -> B (200 m) with a right turn onto R
(200 m): the section is A, B; cars whose route goes on to R turn off at the end of A
through an internal lane slower than A (netconvert's turning speed), cars on to B go
through. The turners are trips (from A to R): SUMO finds their route, no route file has it. U is
where the through cars come from when a rerouter on A sends them to R.
"""

from __future__ import annotations

from pathlib import Path

import libsumo
import numpy as np
import pytest
from conftest import netconvert, one_phase_program, prior_alone, small_section_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.observe import LaneTable
from macromicro_sumo.deploy.turns import ROUTE_RECHECK_S, Turns, turn_limits
from macromicro_sumo.road.physics import NEXT_LIMIT_COLUMN
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.inputs import read_net
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run


def _turn_net(folder: Path, mode: str = "off", rerouter: bool = False) -> tuple:
    nodes = (
        '<node id="u" x="-100" y="0"/>'
        '<node id="n0" x="0" y="0"/><node id="j" x="300" y="0" type="traffic_light"/>'
        '<node id="n2" x="500" y="0"/><node id="s0" x="300" y="-200"/>'
    )
    edges = (
        '<edge id="U" from="u" to="n0" numLanes="1" speed="15"/>'
        '<edge id="A" from="n0" to="j" numLanes="1" speed="15"/>'
        '<edge id="B" from="j" to="n2" numLanes="1" speed="15"/>'
        '<edge id="R" from="j" to="s0" numLanes="1" speed="15"/>'
    )
    net = netconvert(folder, nodes, edges)
    green = one_phase_program(folder, "j", "GG", "green")
    routes = folder / "r.rou.xml"
    routes.write_text(
        '<routes>\n    <vType id="car" length="5" minGap="2.5"/>\n'
        f'    <route id="through" edges="{"U A B" if rerouter else "A B"}"/>\n'
        '    <flow id="thru" type="car" route="through" begin="0" end="60" period="6" '
        'departSpeed="max"/>\n'
        '    <flow id="turn" type="car" begin="3" end="60" period="6" departSpeed="max" '
        'from="A" to="R"/>\n</routes>\n'
    )
    extra = (green,)
    if rerouter:  # every car entering A sent to R: the files' through route turns then
        extra += (folder / "rerouter.add.xml",)
        extra[-1].write_text(
            '<additional>\n    <rerouter id="off" edges="A">\n'
            '        <interval begin="0" end="1000"><destProbReroute id="R"/></interval>\n'
            "    </rerouter>\n</additional>\n"
        )
    sc = small_section_scenario(
        folder, net, routes, ["A", "B"], instrumented={"ids": ["probe"]},
        simulation={"warmup_s": 0.0, "duration_s": 80.0, "n_runs": 2},
        detectors={"interval_s": 40.0}, deploy={"turns": mode}, additional=extra,
    )  # fmt: skip
    opts = SumoOptions(net, extra, 0.5, 5, route_files=(routes,), user_demand=True)
    return sc, net, routes, opts


def _via_speed(net: Path) -> float:
    n = read_net(net, with_internal=True)
    (con,) = [c for c in n.getEdge("A").getLanes()[0].getOutgoing() if c.getTo().getID() == "R"]
    return float(n.getLane(con.getViaLaneID()).getSpeed())


def _on_a(sim: Simulation, want: int) -> list[str]:
    """Step until ``want`` vehicles drive on A; their IDs."""
    for _ in range(200):
        sim.step()
        st = sim.vehicle_states()
        on = [v for v, lane in zip(st.ids, st.lanes, strict=True) if lane == "A_0"]
        if len(on) >= want:
            return on
    raise AssertionError("no vehicles on A")


def test_a_turner_exits_at_its_junction_with_the_turn_s_limit(tmp_path: Path) -> None:
    """Routes from SUMO: the trip's (from A to R) SUMO found, turning at the end of A (edge
    0) with the internal lane's limit (below A's 15), its line at A's end; the through
    car goes on (NaN). A vehicle is asked once per junction edge (a second call reads
    nothing: the route query is broken, it still answers) and dropped off it."""
    _, net, _, opts = _turn_net(tmp_path)
    section = read_section(net, ["A", "B"], False)
    via = _via_speed(net)
    assert via < 15.0
    assert turn_limits(net, section)[(0, "R")] == via
    turns = Turns(section, net, 0.5)
    assert turns.junction.tolist() == [True, False]  # an open section's last edge: none
    assert turns.any and not Turns(read_section(net, ["A"], False), net).any  # A: the end
    line = float(section.offsets_m[0] + section.lengths_m[0])
    sim = Simulation(opts)
    try:
        on = _on_a(sim, 2)
        turner = next(v for v in on if v.startswith("turn"))
        thru = next(v for v in on if v.startswith("thru"))
        assert sim.route_ahead(turner) == ("A", "R") and sim.route_ahead(thru) == ("A", "B")
        lanes = LaneTable(section)
        vids = [thru, turner, "elsewhere"]
        codes = lanes.codes(["A_0", "A_0", "B_0"])
        idx, limit, at = turns.ahead(vids, lanes, codes, np.full(3, 100.0))
        assert idx.tolist() == [1] and limit.tolist() == [via] and at.tolist() == [line]
        assert set(turns.read) == {thru, turner}
        past = turns.ahead(vids, lanes, codes, np.full(3, line + 1.0))  # beyond its line
        assert past[0].size == 0
        turns.turn_at = None  # asked again, this would fail
        again = turns.ahead(vids, lanes, codes, np.full(3, 100.0))
        assert again[0].tolist() == [1]
        gone = turns.ahead(vids[:1], lanes, codes[:1], np.full(1, 100.0))
        assert gone[0].size == 0 and set(turns.read) == {thru}  # pruned: not seen on A
    finally:
        sim.close()


def test_a_car_a_rerouter_sends_off_the_section_turns(tmp_path: Path) -> None:
    """A rerouter on A (destProbReroute R): the through cars of the route file ("U A B")
    turn at A's end; the route SUMO holds when they drive on A says so, and ``ahead`` hands
    them its limit. The file's route alone would have taken them as through."""
    _, net, _, opts = _turn_net(tmp_path, rerouter=True)
    section = read_section(net, ["A", "B"], False)
    turns = Turns(section, net, 0.5)
    sim = Simulation(opts)
    try:
        on = _on_a(sim, 2)
        thru = [v for v in on if v.startswith("thru")]
        assert thru and all(sim.route_ahead(v) == ("A", "R") for v in thru)
        lanes = LaneTable(section)
        codes = lanes.codes(["A_0"] * len(thru))
        idx, limit, _ = turns.ahead(thru, lanes, codes, np.full(len(thru), 50.0))
        assert idx.tolist() == list(range(len(thru))) and (limit == _via_speed(net)).all()
    finally:
        sim.close()


def test_a_route_changed_on_the_junction_edge_is_read_again(tmp_path: Path) -> None:
    """A through car whose route SUMO changes while it drives on A (a TraCI changeTarget, as
    a rerouting device's periodic reroute would) is taken as going on until ``ahead`` asks
    again, ``ROUTE_RECHECK_S`` after its read, and as a turner from then on (before the fix
    it stayed a through car to the end of A)."""
    _, net, _, opts = _turn_net(tmp_path)
    section = read_section(net, ["A", "B"], False)
    turns = Turns(section, net, 0.5)
    assert turns.recheck == round(ROUTE_RECHECK_S / 0.5) > 1
    sim = Simulation(opts)
    try:
        on = _on_a(sim, 2)
        thru = next(v for v in on if v.startswith("thru"))
        lanes = LaneTable(section)
        codes = lanes.codes(["A_0"])
        first = turns.ahead([thru], lanes, codes, np.full(1, 50.0))
        assert first[0].size == 0  # read: through
        libsumo.vehicle.changeTarget(thru, "R")
        assert sim.route_ahead(thru) == ("A", "R")
        seen = [turns.ahead([thru], lanes, codes, np.full(1, 50.0))[0].size for _ in range(8)]
        k = turns.recheck - 1  # calls before the read is due again
        assert seen[:k] == [0] * k and seen[k:] == [1] * (8 - k), seen
        assert turns.read[thru][1] == _via_speed(net)
    finally:
        sim.close()


def _turn_speeds(df, net: Path) -> np.ndarray:
    """The turners' recorded speeds on A's last 5 m."""
    line = float(read_section(net, ["A", "B"], False).lengths_m[0])
    turner = df["vehicle_id"].str.startswith("turn") & df["arc_m"].between(line - 5.0, line)
    return df.loc[turner, "speed_mps"].to_numpy()


def _deploy(tmp_path: Path, mode: str, cross_krauss: dict) -> tuple:
    sc, net, _, opts = _turn_net(tmp_path, mode)
    section = read_section(net, ["A", "B"], False)
    seen: list[np.ndarray] = []
    act = prior_alone(cross_krauss)

    def spy(obs: np.ndarray) -> np.ndarray:
        seen.append(obs.copy())
        return act(obs)

    drv = SectionSpeedDriver(sc, section, 0, spy, "sumo")
    sim = Simulation(opts)
    try:
        df, stats = record_run(sim, sc, section, 0, drv)
    finally:
        sim.close()
    return df, stats, np.concatenate(seen), net, drv


@pytest.mark.parametrize("mode", ["off", "handover"])
def test_turners_handed_over_before_the_line_come_to_the_turn_slower(
    tmp_path: Path, cross_krauss: dict, mode: str
) -> None:
    """Driven by the prior (residual 0), the turners cross A's last 5 m at A's 15 m/s, far
    above the turn's limit and SUMO's own drivers ("off"; on drawn arterial 528 SUMO then
    braked such turners at 5-9 m/s^2 inside the turn); handed to SUMO before the line
    ("handover") they come to it as SUMO's own drivers do (within 0.5 m/s of their fastest),
    no emergency braking. 0 collisions, 0 teleports either way."""
    df, stats, _, net, drv = _deploy(tmp_path, mode, cross_krauss)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    sc, _, _, opts = _turn_net(tmp_path)
    sim = Simulation(opts)
    try:
        own, _ = record_run(sim, sc, read_section(net, ["A", "B"], False), 0)
    finally:
        sim.close()
    v, v_own = _turn_speeds(df, net), _turn_speeds(own, net)
    assert len(v) > 5 and len(v_own) > 5
    if mode == "off":
        assert drv.turns is None
        assert v.max() > 14.0 > v_own.max() + 3.0
    else:
        assert v.max() < v_own.max() + 0.5 and drv.stats.emergency_brakings == 0


def test_a_turner_s_look_ahead_is_the_turn_s_limit_at_its_line(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """deploy.turns "limit": a driven turner on A sees the turn's limit as its next limit,
    its distance the line's (the through cars the next edge's, 15 m/s at B's start)."""
    _, _, obs, net, _ = _deploy(tmp_path, "limit", cross_krauss)
    nxt = obs[:, NEXT_LIMIT_COLUMN]
    via = _via_speed(net)
    assert np.isclose(nxt, via).any() and np.isclose(nxt, 15.0).any()
    section = read_section(net, ["A", "B"], False)
    turn = np.isclose(nxt, via)
    line, b_start = section.lengths_m[0], section.offsets_m[1]
    # distance to the line < distance to B's start for the same position; both positive
    assert (obs[turn, NEXT_LIMIT_COLUMN + 1] >= 0).all()
    assert (obs[turn, NEXT_LIMIT_COLUMN + 1] <= line).all() and b_start > line

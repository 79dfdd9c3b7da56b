"""``deploy.turn_gap``: a commanded turner that must change lanes before its junction slows
for a gap on its turn lane, and the commanded follower there opens one, as SUMO's lane
changer (LC2013) asks of its own drivers (``deploy.turn_gap.turn_gap_caps``), on a real
network through libsumo.

A (400 m, two lanes, 15 m/s) -> a light j -> B (through, from lane 1 only) or R (the turn,
from lane 0 only). R's link is red for the first 70 s: a flow of turners on lane 0 queues
back from the line. At 40 s turner "t" enters on lane 1 beside that flow and must reach
lane 0 before the line.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import sumolib
from conftest import netconvert, prior_alone, small_section_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.turn_gap import (
    TURN_GAP_TOLERANCE_MPS,
    asked_lanes,
    change_sides,
    drop_lanes,
    gap_caps,
    junction_lanes,
    turn_gap_caps,
)
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run

# A_0 onto R, A_1 onto B; ``DROP``: A_0 leads nowhere (a lane drop), A_1 onto B and R.
CONS = (
    '<connection from="A" to="R" fromLane="0" toLane="0"/>'
    '<connection from="A" to="B" fromLane="1" toLane="0"/>'
)
DROP = (
    '<connection from="A" to="R" fromLane="1" toLane="0"/>'
    '<connection from="A" to="B" fromLane="1" toLane="0"/>'
)


def _gap_net(
    folder: Path, gap: str, through: str = "", reach: str = "plain", cons: str = CONS
) -> tuple:
    nodes = (
        '<node id="n0" x="0" y="0"/><node id="j" x="400" y="0" type="traffic_light"/>'
        '<node id="n2" x="600" y="0"/><node id="s0" x="400" y="-200"/>'
    )
    edges = (
        '<edge id="A" from="n0" to="j" numLanes="2" speed="15"/>'
        '<edge id="B" from="j" to="n2" numLanes="1" speed="15"/>'
        '<edge id="R" from="j" to="s0" numLanes="1" speed="15"/>'
    )
    net = netconvert(folder, nodes, edges, cons)
    a = sumolib.net.readNet(str(net)).getEdge("A")
    link = {c.getTo().getID(): c.getTLLinkIndex() for cs in a.getOutgoing().values() for c in cs}

    def state(r: str) -> str:
        s = ["G", "G"]
        s[link["R"]] = r
        return "".join(s)

    prog = folder / "p.add.xml"
    prog.write_text(
        '<additional>\n    <tlLogic id="j" type="static" programID="q" offset="0">\n'
        f'        <phase duration="70" state="{state("r")}"/>\n'
        f'        <phase duration="1000" state="{state("G")}"/>\n    </tlLogic>\n</additional>\n'
    )
    routes = folder / "r.rou.xml"
    routes.write_text(
        '<routes>\n    <vType id="car" length="5" minGap="2.5"/>\n'
        '    <route id="off" edges="A R"/>\n'
        '    <flow id="q" type="car" route="off" begin="0" end="60" period="2" departLane="0" '
        f'departSpeed="max"/>\n{through}'  # departures in order: SUMO reads them so
        '    <vehicle id="t" type="car" route="off" depart="40" departLane="1" '
        'departSpeed="max"/>\n</routes>\n'
    )
    sc = small_section_scenario(
        folder, net, routes, ["A", "B"], instrumented={"ids": ["probe"]},
        simulation={"warmup_s": 0.0, "duration_s": 100.0, "n_runs": 2},
        detectors={"interval_s": 50.0}, additional=(prog,),
        # the junction and start rules off, as before stop 49 moved their defaults
        deploy={"turn_gap": gap, "merge_reach": reach, "keep_clear": "off", "yellow": "onset",
                "start_dawdle": 0.0, "start_reaction_s": 0.0},
    )  # fmt: skip
    opts = SumoOptions(net, (prog,), 0.5, 5, route_files=(routes,), user_demand=True)
    return sc, net, opts


def _turner(tmp_path: Path, gap: str | None, cross_krauss: dict, reach: str = "plain") -> tuple:
    """Turner t's rows (lane, arc, speed) of one run: commanded by the prior with
    ``deploy.turn_gap = gap`` and ``deploy.merge_reach = reach``, or SUMO's own drivers alone
    (None); the run's stats."""
    sc, net, opts = _gap_net(tmp_path, gap or "off", reach=reach)
    section = read_section(net, ["A", "B"], False)
    act = prior_alone(cross_krauss)
    drv = None if gap is None else SectionSpeedDriver(sc, section, 0, act, "sumo")
    sim = Simulation(opts)
    try:
        df, stats = record_run(sim, sc, section, 0, drv)
    finally:
        sim.close()
    return df[df["vehicle_id"] == "t"], stats, drv


@pytest.mark.parametrize(
    ("gap", "reach"), [("off", "plain"), ("sumo", "plain"), ("sumo", "occupation")]
)
def test_a_commanded_turner_reaches_its_turn_lane_with_turn_gap(
    tmp_path: Path, cross_krauss: dict, gap: str, reach: str
) -> None:
    """SUMO's own t changes to lane 0 and joins the queue's end (about 242 m). Commanded,
    without the setting, it drives on beside the queue at 15 m/s, its follower on lane 0
    never letting it in, and stands at the line on lane 1 until the queue has gone; with
    ``turn_gap = "sumo"`` it reaches lane 0 before the queue and stands at its end as SUMO's
    own does, with ``merge_reach = "occupation"`` too (t changes from lane 1, which carries
    on: not a lane drop). 0 collisions, 0 teleports, no emergency braking."""
    t, stats, drv = _turner(tmp_path, gap, cross_krauss, reach)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    assert drv.stats.emergency_brakings == 0
    stood = t[(t["speed_mps"] < 0.5)]
    changed = t[t["lane_index"] == 0]["arc_m"].min()
    if gap == "off":  # on lane 1 to the line, standing there until the queue has gone
        assert changed > 385.0
        assert (stood["lane_index"] == 1).all() and (stood["arc_m"] > 385.0).all()
        assert len(stood) >= 10
    else:
        assert changed < 240.0
        assert (stood["lane_index"] == 0).all() and stood["arc_m"].between(238.0, 246.0).all()
        assert len(stood) >= 10


def test_occupation_leaves_the_turners_to_the_plain_reach(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """Occupation acts only on the lanes whose chain ends (``drop_chain_lanes``): here A_0,
    exit-only for the through route, and the junction's internal lanes; t's change from
    A_1, which carries on, is a turner's. So nobody on A_1 is handed over at the usable
    distance nor yielded to, and with every queued turner on A_0 needing no change, the
    run with occupation is the plain one to the bit (before, occupation's hand-over and
    yield took t too: its queue ended a car farther back, t standing at 234 m)."""
    (tmp_path / "p").mkdir()
    (tmp_path / "o").mkdir()
    plain, _, _ = _turner(tmp_path / "p", "sumo", cross_krauss, "plain")
    occ, stats, drv = _turner(tmp_path / "o", "sumo", cross_krauss, "occupation")
    assert drv.occupation and drv.yield_all
    assert "A_0" in drv.drop_lanes and "A_1" not in drv.drop_lanes
    assert all(lane == "A_0" or lane.startswith(":") for lane in drv.drop_lanes)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    cols = ["time_s", "lane_index", "arc_m", "speed_mps"]
    assert len(occ) > 50
    assert occ[cols].reset_index(drop=True).equals(plain[cols].reset_index(drop=True))


def test_sumo_s_own_turner_joins_the_queue_s_end(tmp_path: Path, cross_krauss: dict) -> None:
    """The reference: SUMO's own drivers, no command, t changes to lane 0 before 150 m and
    stands at the queue's end, 240-245 m, where the commanded one with the setting stands."""
    t, stats, _ = _turner(tmp_path, None, cross_krauss)
    assert stats["collisions"] == 0
    assert t[t["lane_index"] == 0]["arc_m"].min() < 150.0
    stood = t[t["speed_mps"] < 0.5]
    assert (stood["lane_index"] == 0).all() and stood["arc_m"].between(238.0, 246.0).all()


def test_gap_caps_take_sumo_s_speed_only_where_it_asked_for_less() -> None:
    """Own speeds within the tolerance (dawdling) or NaN (not asked) cap nothing; one asked
    for less is capped to it, but not below one step's braking at the vType's decel."""
    tol = TURN_GAP_TOLERANCE_MPS
    own = np.array([np.nan, 10.0 - tol / 2, 8.5, 0.0])
    speed = np.full(4, 10.0)
    got = gap_caps(own, speed, np.full(4, 4.5), 0.5)
    assert np.isinf(got[:2]).all() and got[2] == 8.5 and got[3] == 10.0 - 4.5 * 0.5


def test_change_sides_ask_only_on_junction_edges(tmp_path: Path) -> None:
    """A (two lanes, a connection off the section to R) is a junction edge, B (the open
    section's last edge) is not: A's lane 0 asks to the left only, lane 1 to the right only;
    B, a lane off the section and a junction's internal lane ask nothing. A section without
    a junction edge (A alone: its end is the section's) has no lane to ask on."""
    _, net, _ = _gap_net(tmp_path, "off")
    section = read_section(net, ["A", "B"], False)
    on = junction_lanes(section, net)
    assert on == {"A_0", "A_1"}
    at, sides = change_sides(section, ["A_0", "A_1", "B_0", "R_0", ":j_0_0"], on)
    assert at == [0, 1] and sides == [1, -1]
    assert junction_lanes(read_section(net, ["A"], False), net) == frozenset()


def test_drop_lanes_are_the_junction_lanes_that_lead_nowhere(tmp_path: Path) -> None:
    """With ``DROP`` A_0 leads nowhere (a lane drop): every vehicle on it must leave it; A_0
    leading only off the section (``CONS``, an exit-only lane) is no drop. ``change_sides``
    skips the lanes it is told to."""
    (tmp_path / "x").mkdir()
    (tmp_path / "d").mkdir()
    _, net, _ = _gap_net(tmp_path / "x", "off")
    section = read_section(net, ["A", "B"], False)
    assert drop_lanes(section, junction_lanes(section, net)) == frozenset()
    _, net, _ = _gap_net(tmp_path / "d", "off", cons=DROP)
    section = read_section(net, ["A", "B"], False)
    on = junction_lanes(section, net)
    assert on == {"A_0", "A_1"} and drop_lanes(section, on) == {"A_0"}
    assert asked_lanes(section, net, occupation=True) == {"A_1"}
    assert asked_lanes(section, net, occupation=False) == on
    at, sides = change_sides(section, ["A_0", "A_1", "B_0"], asked_lanes(section, net, True))
    assert at == [1] and sides == [-1]


# Through traffic on lane 1 and through car "d" on lane 0 (with ``CONS`` it leads only to R,
# with ``DROP`` nowhere) behind the turners' queue at the red: d must change to lane 1,
# blocked by the flow there.
THROUGH = (
    '    <route id="on" edges="A B"/>\n'
    '    <flow id="f" type="car" route="on" begin="0" end="38" period="1" departLane="1" '
    'departSpeed="max"/>\n'
    '    <vehicle id="d" type="car" route="on" depart="20" departLane="0" departSpeed="max"/>\n'
)


def _asked(folder: Path, cons: str) -> dict[str, set[str]]:
    """Every vehicle SUMO's own (nothing commanded): per ``merge_reach``, whom
    ``turn_gap_caps`` asks some step; at every step occupation's caps are plain's."""
    folder.mkdir()
    sc, net, opts = _gap_net(folder, "sumo", THROUGH, cons=cons)
    section = read_section(net, ["A", "B"], False)
    on = {
        r: asked_lanes(section, net, occupation=r == "occupation") for r in ("plain", "occupation")
    }
    by = {
        reach: dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, merge_reach=reach))
        for reach in ("plain", "occupation")
    }
    asked: dict[str, set[str]] = {"plain": set(), "occupation": set()}
    sim = Simulation(opts)
    try:
        for _ in range(160):
            sim.step()
            # Read 50 m/s faster than they are: SUMO's own speed is below that for every
            # vehicle its lane changer asked (a driven one's command is what runs ahead).
            now = sim.vehicle_states()
            st = dataclasses.replace(now, speed_mps=now.speed_mps + 50.0)
            rows = np.arange(len(st.ids))
            shape = {v: (5.0, 2.5, 4.5) for v in st.ids}
            got = {r: turn_gap_caps(by[r], section, shape, st, rows, None, on[r]) for r in by}
            for r, cap in got.items():
                if cap is not None:
                    asked[r] |= {st.ids[i] for i in np.isfinite(cap).nonzero()[0]}
            if got["occupation"] is not None:  # occupation asks fewer, never another cap
                plain = got["plain"]
                assert plain is not None
                fin = np.isfinite(got["occupation"])
                assert np.array_equal(got["occupation"][fin], plain[fin])
    finally:
        sim.close()
    return asked


def test_with_occupation_the_lane_drop_changer_is_not_asked(tmp_path: Path) -> None:
    """A_0 a lane drop (``DROP``): at ``merge_reach = "plain"`` through car d (blocked
    leaving A_0) and its followers on A_1 are asked some step; at "occupation" nobody (the
    merge's is d). A_0 exit-only (``CONS``): d is a changer as a turner is, asked at both
    (a turner changing from a lane that carries on, with occupation too:
    ``test_a_commanded_turner_reaches_its_turn_lane_with_turn_gap``)."""
    drop = _asked(tmp_path / "drop", DROP)
    assert "d" in drop["plain"] and any(v.startswith("f.") for v in drop["plain"]), drop
    assert not drop["occupation"], drop
    exit_only = _asked(tmp_path / "exit", CONS)
    assert "d" in exit_only["plain"] and exit_only["occupation"] == exit_only["plain"]

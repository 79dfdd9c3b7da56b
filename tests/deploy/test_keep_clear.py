"""``deploy.keep_clear``: a driven vehicle does not enter a signalised junction it cannot
leave (``deploy.keep_clear``), as SUMO's own drivers, in real SUMO and in the pure rule."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sumolib
from conftest import netconvert
from deploy_nets import CAR
from section_files import section_scenario
from test_safety import _run_section

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.keep_clear import DEFAULT_SHAPE, KeepClear, lane_rooms, signal_ends
from macromicro_sumo.deploy.observe import states_of
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario

# The approach and the lane past the light, node to node [m] (netconvert shortens both).
A_M, B_M = 150.0, 45.0
BLOCKERS = 1  # standing on B, 5.1 m of room behind it


def _blocked_exit(tmp_path: Path, keep_clear: str, ids: list[str]) -> Path:
    """A (150 m) -> a light, green throughout, with a side road across -> B (45 m node to
    node), on which ``BLOCKERS`` cars stand (a stop of 1000 s) with 5.1 m behind the last;
    3 cars leave A 2 s apart toward B.
    ``ids``: the instrumented ones (SUMO drives them), the blockers always."""
    folder = tmp_path / "net"
    folder.mkdir(parents=True, exist_ok=True)
    # A crossing side road (S -> T): the main road's link has foes, where SUMO keeps clear.
    nodes = (
        f'<node id="n0" x="0" y="0"/>\n<node id="tl" x="{A_M:g}" y="0" type="traffic_light"/>\n'
        f'<node id="n2" x="{A_M + B_M:g}" y="0"/>\n<node id="s0" x="{A_M:g}" y="60"/>\n'
        f'<node id="s1" x="{A_M:g}" y="-60"/>'
    )
    edges = "\n".join(
        f'<edge id="{e}" from="{a}" to="{b}" numLanes="1" speed="14"/>'
        for e, a, b in (("A", "n0", "tl"), ("B", "tl", "n2"), ("S", "s0", "tl"), ("T", "tl", "s1"))
    )
    net = netconvert(folder, nodes, edges)
    links = len(sumolib.net.readNet(str(net), withPrograms=True).getTLS("tl").getConnections())
    block = "\n".join(
        f'<vehicle id="b{k}" type="car" depart="{0.5 * k:g}" departPos="{10.1 + 7.6 * (BLOCKERS - 1 - k):g}" '
        f'departSpeed="0"><route edges="B"/><stop lane="B_0" endPos="{10.1 + 7.6 * (BLOCKERS - 1 - k):g}" '
        'duration="1000"/></vehicle>'
        for k in range(BLOCKERS)
    )
    cars = "\n".join(
        f'<vehicle id="c{k}" type="car" depart="{2 + 2 * k}" departSpeed="max">'
        '<route edges="A B"/></vehicle>'
        for k in range(3)
    )
    (folder / "cars.rou.xml").write_text(f"<routes>\n{CAR}\n{block}\n{cars}\n</routes>\n")
    (folder / "light.add.xml").write_text(
        '<additional>\n<tlLogic id="tl" type="static" programID="p" offset="0">\n'
        f'<phase duration="1000" state="{"G" * links}"/>\n</tlLogic>\n</additional>\n'
    )
    blockers = [f"b{k}" for k in range(BLOCKERS)]
    return section_scenario(
        tmp_path / f"kc_{keep_clear}.toml",
        net,
        folder / "cars.rou.xml",
        ["A", "B"],
        seed=3,
        penetration=0.0,
        simulation={"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 1},
        detectors={"interval_s": 30.0},
        deploy={"keep_clear": keep_clear},
        instrumented={"ids": blockers + ids},
    )


def _stopper(obs: np.ndarray) -> np.ndarray:
    """A policy that drives at full throttle but stops 2.5 m behind what it observes ahead
    (obs[:, 2]: the front-to-front spacing to its leader or stop, a car of 5 m ahead)."""
    room = np.maximum(obs[:, 2] - 7.5, 0.0)
    return np.clip((np.sqrt(2.0 * 4.5 * room) - obs[:, 0]) / 0.5, -4.5, 2.6)


def _furthest(tmp_path: Path, keep_clear: str, sumo_drives: bool) -> tuple[float, dict]:
    """How far [m] past A's end (its stop line) any of the 3 approaching cars reached, and
    the run's stats: a
    full-throttle policy drives them (or SUMO, ``sumo_drives``)."""
    ids = [f"c{k}" for k in range(3)] if sumo_drives else []
    sc = load_scenario(_blocked_exit(tmp_path, keep_clear, ids))
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B"], False)
    drv = SectionSpeedDriver(sc, section, 0, _stopper, "sumo")
    light = sc.resolve(sc.network.net_file).parent / "light.add.xml"
    df, stats = _run_section(sc, drv, (light,))
    cars = df[df["vehicle_id"].str.startswith("c")]
    assert set(cars["vehicle_id"]) == {"c0", "c1", "c2"}
    a_len = sumolib.net.readNet(str(sc.resolve(sc.network.net_file))).getEdge("A").getLength()
    return float(cars["arc_m"].max()) - a_len, stats


def test_a_driven_car_waits_at_a_green_line_it_cannot_clear_as_sumos(tmp_path: Path) -> None:
    """The lane past a green light has 5.1 m of room behind a standing car: SUMO's own
    drivers wait before the line (their fronts at most at A's end), and so do driven cars
    under a policy that stops only for what it observes, with ``keep_clear = "lane"`` (the
    line a standing obstacle in their observation); with "off" the first drives into the
    junction behind the standing car. No collision, no teleport."""
    reached = {}
    for name, mode, sumo_drives in (
        ("sumo", "off", True),
        ("lane", "lane", False),
        ("off", "off", False),
    ):
        reached[name], stats = _furthest(tmp_path / name, mode, sumo_drives)
        assert stats["collisions"] == 0 and stats["teleports"] == 0, (name, stats)
    assert reached["sumo"] <= 0.0, reached
    assert reached["lane"] <= 0.0, reached
    assert reached["off"] > 1.0, reached


def test_the_room_is_up_to_the_upstream_most_waiting_vehicle() -> None:
    """SUMO's getSpaceTillLastStanding: the back of the upstream-most vehicle below the
    waiting speed, less length and minGap of each moving one behind it; none waiting: no
    entry (room further on)."""
    lanes = ["B_0", "B_0", "B_0", "C_0"]
    pos = np.array([40.0, 20.0, 12.0, 30.0])
    speed = np.array([0.0, 0.05, 3.0, 2.0])
    brutto, length = np.full(4, 7.5), np.full(4, 5.0)
    rooms = lane_rooms(lanes, pos, speed, brutto, length, 0.1)
    assert rooms == {"B_0": 20.0 - 5.0 - 7.5}  # behind the one at 20 m, less the mover at 12
    assert lane_rooms(lanes, pos, speed, brutto, length, 5.0) == {"B_0": 7.0, "C_0": 25.0}


def test_the_lanes_ending_at_a_signal(tmp_path: Path) -> None:
    """Only the approach controlled by the light (A, and the side road S) ends at one."""
    sc = load_scenario(_blocked_exit(tmp_path, "lane", []))
    ends = signal_ends(str(sc.resolve(sc.network.net_file)))
    assert "A_0" in ends and "S_0" in ends and "B_0" not in ends


def test_the_driver_owns_its_keep_clear_and_each_shape_is_kept_from_first_sight(
    tmp_path: Path,
) -> None:
    """A driver with ``keep_clear`` on owns a ``KeepClear`` (none with "off"); the rooms of
    the lanes asked about are those ``lane_rooms`` gives over every vehicle on the road, from
    the lengths and minGaps kept when each vehicle was first met (an unknown one: SUMO's
    passenger, asked again next time)."""
    sc = load_scenario(_blocked_exit(tmp_path / "lane", "lane", []))
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B"], False)
    drv = SectionSpeedDriver(sc, section, 0, _stopper, "sumo")
    assert isinstance(drv.keep_clear, KeepClear) and drv.keep_clear.waiting_mps == 0.1
    off = load_scenario(_blocked_exit(tmp_path / "off", "off", []))
    assert SectionSpeedDriver(off, section, 0, _stopper, "sumo").keep_clear is None
    kc = KeepClear("lane1", section, 0.5)
    st = states_of(
        {
            "a": ("B_0", 40.0, 0.0, 0.0),
            "b": ("A_0", 30.0, 0.5, 0.0),
            "c": ("B_0", 20.0, 0.5, 0.0),
            "d": ("B_0", 12.0, 3.0, 0.0),
            "e": ("S_0", 9.0, 0.0, 0.0),
        }
    )
    shape_of = {"a": (4.0, 2.0, 4.5), "b": (12.0, 3.0, 4.0), "d": (7.0, 2.5, 4.5)}
    kc.meet(st.ids, shape_of)
    assert kc.brutto_m == {"a": 6.0, "b": 15.0, "d": 9.5} and "c" not in kc.length_m
    shape_of["a"] = (99.0, 99.0, 4.5)  # met already: kept as first seen
    length = np.array([(shape_of.get(v) or DEFAULT_SHAPE)[0] for v in st.ids])
    length[0] = 4.0
    brutto = np.array([sum((shape_of.get(v) or DEFAULT_SHAPE)[:2]) for v in st.ids])
    brutto[0] = 6.0
    whole = lane_rooms(st.lanes, st.pos_m, st.speed_mps, brutto, length, 1.0)
    assert kc.rooms(st, {"B_0"}) == {"B_0": whole["B_0"]} == {"B_0": 20.0 - 5.0 - 9.5}
    assert kc.rooms(st, {"B_0", "S_0"}) == {k: whole[k] for k in ("B_0", "S_0")}
    assert kc.rooms(st, {"C_0"}) == {}
    shape_of["c"] = (3.0, 1.0, 4.5)  # first known now: kept from here on
    kc.meet(st.ids, shape_of)
    assert kc.brutto_m["c"] == 4.0 and kc.rooms(st, {"B_0"}) == {"B_0": 20.0 - 3.0 - 9.5}
    with pytest.raises(ValueError, match="keep_clear"):
        KeepClear("off", section, 0.5)


def test_a_call_for_some_cars_keeps_the_others_holds(tmp_path: Path) -> None:
    """``KeepClear.lines`` decides only the cars it is asked about: the first sight's call
    for new drivers alone keeps a held car's hold (it used to drop it); a car asked about
    and not held now loses it; a car gone from the road is forgotten."""
    sc = load_scenario(_blocked_exit(tmp_path, "lane", []))
    net = str(sc.resolve(sc.network.net_file))
    section = read_section(net, ["A", "B"], False)
    kc = KeepClear("lane", section, 0.5)
    st = states_of({"c0": ("A_0", 100.0, 0.0, 0.0), "c1": ("A_0", 20.0, 10.0, 0.0)})
    shape_of = {"c0": (5.0, 2.5, 4.5), "c1": (5.0, 2.5, 4.5)}
    kc.held = {"c0"}
    red = np.array([np.inf])  # c1 alone: a green ahead, nobody waiting past: no hold
    out = kc.lines(net, red, ["A_0"], np.array([1]), st, [("c0", 72.5)], ["c1"], shape_of)
    assert out is red and kc.held == {"c0"}
    kc.lines(net, np.array([np.inf, np.inf]), ["A_0", "A_0"], np.array([0, 1]), st,
             [("", -1.0), ("c0", 72.5)], ["c0", "c1"], shape_of)  # fmt: skip
    assert kc.held == set()  # asked about, nothing waiting past the junction
    kc.held = {"gone"}
    kc.lines(net, red, ["A_0"], np.array([1]), st, [("c0", 72.5)], ["c1"], shape_of)
    assert kc.held == set()


@pytest.mark.parametrize("bad", ["on", "yes"])
def test_a_bad_word_is_refused(tmp_path: Path, bad: str) -> None:
    with pytest.raises(Exception, match="keep_clear"):
        load_scenario(_blocked_exit(tmp_path, bad, []))

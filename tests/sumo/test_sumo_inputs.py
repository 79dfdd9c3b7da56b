"""A user's SUMO files: every wrong input is a one-line UserError naming file and element."""

from __future__ import annotations

import gzip
import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from macromicro_sumo.errors import UserError
from macromicro_sumo.sumo.demand import (
    VCLASS_DEFAULT,
    VCLASS_DEFAULTS,
    check_demand,
    check_vehicle_ids,
)
from macromicro_sumo.sumo.inputs import (
    SumoInputs,
    auto_detectors_xml,
    read_net,
    resolve_inputs,
    user_detectors,
)

NETS = Path(__file__).parents[2] / "sumo_nets"
CORRIDOR = NETS / "netgen_corridor" / "corridor.net.xml"  # edges e0..e6, lanes 2 1 3 1 2 3 1


@pytest.fixture
def net_file(tmp_path: Path) -> Path:
    return Path(shutil.copy(CORRIDOR, tmp_path / "corridor.net.xml"))


def _inputs(net_file: Path, routes=(), adds=()) -> SumoInputs:
    return SumoInputs(net_file, tuple(routes), tuple(adds), None)


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_read_net_rejects_non_network_files(tmp_path: Path) -> None:
    routes = _write(tmp_path / "demand.xml", "<routes/>")
    with pytest.raises(UserError, match=r"demand\.xml: not a SUMO network \(root element <routes>"):
        read_net(routes)
    text = _write(tmp_path / "notes.net.xml", "this is not xml")
    with pytest.raises(UserError, match=r"notes\.net\.xml: not an XML file"):
        read_net(text)


def test_read_net_reads_gzip(tmp_path: Path) -> None:
    gz = tmp_path / "corridor.net.xml.gz"
    gz.write_bytes(gzip.compress(CORRIDOR.read_bytes()))
    net = read_net(gz)
    assert [net.getEdge(f"e{i}").getLaneNumber() for i in range(7)] == [2, 1, 3, 1, 2, 3, 1]
    bad = tmp_path / "x.net.xml.gz"
    bad.write_bytes(gzip.compress(b"<additional/>"))
    with pytest.raises(UserError, match=r"x\.net\.xml\.gz: not a SUMO network .*<additional>"):
        read_net(bad)


def test_sumocfg_resolves_relative_to_its_folder(tmp_path: Path, net_file: Path) -> None:
    sub = tmp_path / "cfg"
    sub.mkdir()
    r1 = _write(tmp_path / "a.rou.xml", "<routes/>")
    r2 = _write(tmp_path / "b.rou.xml", "<routes/>")
    add = _write(tmp_path / "d.add.xml", "<additional/>")
    extra = _write(tmp_path / "extra.rou.xml", "<routes/>")
    cfg = _write(
        sub / "x.sumocfg",
        "<sumoConfiguration><input>"
        '<net-file value="../corridor.net.xml"/>'
        '<route-files value="../a.rou.xml, ../b.rou.xml"/>'
        '<additional-files value="../d.add.xml"/>'
        "</input></sumoConfiguration>",
    )
    got = resolve_inputs(cfg, None, [extra], [], "scen.toml")
    assert got.net_file.resolve() == net_file.resolve()
    assert [p.resolve() for p in got.route_files] == [r1, r2, extra]
    assert [p.resolve() for p in got.additional_files] == [add]
    assert got.sumocfg == cfg


def test_sumocfg_errors(tmp_path: Path, net_file: Path) -> None:
    wrong = _write(tmp_path / "build.netccfg", "<netconvertConfiguration/>")
    with pytest.raises(UserError, match=r"build\.netccfg: not a SUMO configuration .*<netconvert"):
        resolve_inputs(wrong, None, [], [], "scen.toml")
    missing = _write(
        tmp_path / "m.sumocfg",
        '<sumoConfiguration><input><net-file value="corridor.net.xml"/>'
        '<route-files value="gone.rou.xml"/></input></sumoConfiguration>',
    )
    with pytest.raises(UserError, match=r"m\.sumocfg: .*gone\.rou\.xml does not exist"):
        resolve_inputs(missing, None, [], [], "scen.toml")
    with pytest.raises(UserError, match=r"scen\.toml: .*nowhere\.add\.xml does not exist"):
        resolve_inputs(None, net_file, [], [tmp_path / "nowhere.add.xml"], "scen.toml")
    with pytest.raises(UserError, match=r"scen\.toml: no network"):
        resolve_inputs(None, None, [], [], "scen.toml")


def test_route_with_missing_edge_is_named(tmp_path: Path, net_file: Path) -> None:
    routes = _write(
        tmp_path / "demand.rou.xml",
        '<routes><vType id="car" length="5"/>'
        '<route id="r1" edges="e0 e1 ghost e3"/>'
        '<vehicle id="v0" type="car" route="r1" depart="0"/></routes>',
    )
    with pytest.raises(
        UserError,
        match=r"demand\.rou\.xml: route 'r1' uses edge 'ghost' which is not in corridor\.net\.xml",
    ):
        check_demand(_inputs(net_file, [routes]), read_net(net_file))


def test_trip_and_nested_route_edges_are_checked(tmp_path: Path, net_file: Path) -> None:
    net = read_net(net_file)
    trip = _write(tmp_path / "t.rou.xml", '<routes><trip id="t7" from="e0" to="e9"/></routes>')
    with pytest.raises(UserError, match=r"t\.rou\.xml: trip 't7' uses edge 'e9'"):
        check_demand(_inputs(net_file, [trip]), net)
    nested = _write(
        tmp_path / "n.rou.xml",
        '<routes><vehicle id="v3" depart="0"><route edges="e0 zz"/></vehicle></routes>',
    )
    with pytest.raises(UserError, match=r"n\.rou\.xml: route of vehicle 'v3' uses edge 'zz'"):
        check_demand(_inputs(net_file, [nested]), net)


def test_vtype_without_length_takes_sumos_default_for_its_class(
    tmp_path: Path, net_file: Path
) -> None:
    routes = _write(
        tmp_path / "demand.rou.xml",
        '<routes><vType id="car" accel="2.0"/><vType id="lorry" vClass="truck" minGap="3"/>'
        '<vType id="bike" vClass="bicycle"/><vType id="bad" length="0"/>'
        '<flow id="f" type="car" from="e0" to="e6" begin="0" end="60" number="5"/>'
        '<flow id="g" type="lorry" from="e0" to="e6" begin="0" end="60" number="5"/>'
        '<flow id="h" type="bike" from="e0" to="e6" begin="0" end="60" number="5"/></routes>',
    )
    got = check_demand(_inputs(net_file, [routes]), read_net(net_file))
    assert (got["car"].length_m, got["car"].min_gap_m) == (5.0, 2.5)
    assert (got["lorry"].length_m, got["lorry"].min_gap_m) == (7.1, 3.0)
    assert (got["bike"].length_m, got["bike"].min_gap_m) == (1.6, 0.5)
    bad = _write(tmp_path / "bad.rou.xml", routes.read_text().replace('type="car"', 'type="bad"'))
    with pytest.raises(UserError, match=r"bad\.rou\.xml: vType 'bad' has length '0'; accepted"):
        check_demand(_inputs(net_file, [bad]), read_net(net_file))


_SUMO_DEFAULTS = """
import json, sys, libsumo, sumolib
classes = json.loads(sys.argv[1])
with open(sys.argv[2], "w") as f:
    f.write("<additional>" + "".join(f'<vType id="t_{c}" vClass="{c}"/>' for c in classes))
    f.write('<vType id="t_none"/></additional>')
libsumo.start([sumolib.checkBinary("sumo"), "-n", sys.argv[3], "-a", sys.argv[2]])
got = {c: [libsumo.vehicletype.getLength(f"t_{c}"), libsumo.vehicletype.getMinGap(f"t_{c}")]
       for c in [*classes, "none"]}
libsumo.close()
print(json.dumps(got))
"""


def test_vclass_defaults_are_sumos_own(tmp_path: Path, net_file: Path) -> None:
    """The table of default lengths and gaps against the SUMO in use (its own process:
    libsumo holds one simulation per process)."""
    classes = [*VCLASS_DEFAULTS, "passenger", "taxi", "evehicle"]
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            _SUMO_DEFAULTS,
            json.dumps(classes),
            str(tmp_path / "t.add.xml"),
            str(net_file),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    got = json.loads(done.stdout.strip().splitlines()[-1])
    want = {c: list(VCLASS_DEFAULTS.get(c, VCLASS_DEFAULT)) for c in [*classes, "none"]}
    assert {c: [round(v, 4) for v in got[c]] for c in got} == want


def test_instrumented_ids_must_name_a_vehicle_of_the_demand(tmp_path: Path, net_file: Path):
    routes = _write(
        tmp_path / "demand.rou.xml",
        '<routes><route id="r" edges="e0 e1 e2 e3 e4 e5 e6"/>'
        '<vehicle id="solo" route="r" depart="0"/><trip id="t1" from="e0" to="e6" depart="1"/>'
        '<flow id="f" route="r" begin="0" end="60" number="5"/></routes>',
    )
    inputs = _inputs(net_file, [routes])
    check_vehicle_ids(inputs, ["solo", "t1", "f.0", "f.4"], "x.toml: instrumented.ids")
    for bad in ("f", "f.", "f.a", "g.0", "Solo"):
        with pytest.raises(
            UserError, match=rf"x\.toml: instrumented\.ids names '{re.escape(bad)}'"
        ):
            check_vehicle_ids(inputs, [bad], "x.toml: instrumented.ids")


def test_vtypes_distribution_and_default(tmp_path: Path, net_file: Path) -> None:
    routes = _write(
        tmp_path / "demand.rou.xml",
        "<routes>"
        '<vTypeDistribution id="mix">'
        '<vType id="a" length="4.5" minGap="2" carFollowModel="IDM" accel="1.2" tau="1.1"'
        ' speedFactor="norm(1,0.1)" probability="0.5"/>'
        '<vType id="b" length="12" probability="0.5"><carFollowing-IDMM accel="0.8"/></vType>'
        "</vTypeDistribution>"
        '<vType id="unused"/>'
        '<route id="r" edges="e0 e1 e2 e3 e4 e5 e6"/>'
        '<flow id="f" type="mix" route="r" begin="0" end="60" number="5"/>'
        '<vehicle id="plain" route="r" depart="0"/>'
        "</routes>",
    )
    got = check_demand(_inputs(net_file, [routes]), read_net(net_file))
    assert set(got) == {"a", "b", "DEFAULT_VEHTYPE"}  # "unused" has no length but no vehicle
    assert got["a"].car_follow_model == "IDM" and got["a"].length_m == 4.5
    assert got["a"].params == {"accel": 1.2, "tau": 1.1, "probability": 0.5}
    assert got["b"].car_follow_model == "IDMM" and got["b"].params["accel"] == 0.8
    assert got["b"].min_gap_m == 2.5
    default = got["DEFAULT_VEHTYPE"]
    assert (default.length_m, default.min_gap_m, default.car_follow_model) == (5.0, 2.5, "Krauss")


def test_undefined_vtype_and_route(tmp_path: Path, net_file: Path) -> None:
    net = read_net(net_file)
    vt = _write(
        tmp_path / "a.rou.xml", '<routes><trip id="t" type="bus" from="e0" to="e6"/></routes>'
    )
    with pytest.raises(UserError, match=r"a\.rou\.xml: trip 't' uses vType 'bus' which is defined"):
        check_demand(_inputs(net_file, [vt]), net)
    rt = _write(
        tmp_path / "b.rou.xml", '<routes><vehicle id="v" route="nope" depart="0"/></routes>'
    )
    with pytest.raises(UserError, match=r"b\.rou\.xml: vehicle 'v' uses route 'nope'"):
        check_demand(_inputs(net_file, [rt]), net)


def test_detector_file_for_another_network(tmp_path: Path, net_file: Path) -> None:
    adds = _write(
        tmp_path / "loops.add.xml",
        '<additional><inductionLoop id="d0" lane="e0_1" pos="10" period="60" file="o.xml"/>'
        '<inductionLoop id="d1" lane="145354574_0" pos="10" period="60" file="o.xml"/>'
        "</additional>",
    )
    with pytest.raises(
        UserError,
        match=r"loops\.add\.xml: detector 'd1' is on lane '145354574_0' which is not in "
        r"corridor\.net\.xml \(a detector file for another network\?\)",
    ):
        user_detectors(_inputs(net_file, adds=[adds]), read_net(net_file))
    # e1 has one lane: lane index 1 does not exist either
    one_lane = _write(
        tmp_path / "l2.add.xml",
        '<additional><e1Detector id="d2" lane="e1_1" pos="1" freq="60" file="o.xml"/></additional>',
    )
    with pytest.raises(UserError, match=r"l2\.add\.xml: detector 'd2' is on lane 'e1_1'"):
        user_detectors(_inputs(net_file, adds=[one_lane]), read_net(net_file))


def test_user_detectors_positions(tmp_path: Path, net_file: Path) -> None:
    net = read_net(net_file)
    e0 = net.getEdge("e0").getLength()
    e1 = net.getEdge("e1").getLength()
    adds = _write(
        tmp_path / "det.add.xml",
        "<additional>"
        '<inductionLoop id="a" lane="e0_0" pos="-10" freq="30" file="out/e1.xml"/>'
        '<laneAreaDetector id="b" lane="e0_1" pos="100" length="50" period="60" file="e2.xml"/>'
        '<laneAreaDetector id="c" lane="e0_0" endPos="-5" length="20" file="e2.xml"/>'
        '<laneAreaDetector id="m" lanes="e0_0 e1_0" pos="500" endPos="40" file="e2.xml"/>'
        "</additional>",
    )
    a, b, c, m = user_detectors(_inputs(net_file, adds=[adds]), net)
    assert (a.kind, a.lane_id, a.length_m, a.period_s) == ("e1", "e0_0", 0.0, 30.0)
    assert a.pos_m == pytest.approx(e0 - 10)
    assert a.file == str((tmp_path / "out" / "e1.xml").resolve())
    assert (b.kind, b.pos_m, b.length_m, b.period_s) == ("e2", 100.0, 50.0, 60.0)
    assert c.pos_m == pytest.approx(e0 - 25) and c.period_s == 900.0
    assert m.lane_ids == ("e0_0", "e1_0") and m.lane_id == "e0_0"
    assert m.length_m == pytest.approx(e0 - 500 + 40)
    assert e1 > 40


def test_auto_detectors_xml_loads_as_additional(tmp_path: Path, net_file: Path) -> None:
    xml = auto_detectors_xml([("e0_0", 100.0), ("e0_0", 350.0), ("e2_2", 12.5)], 60.0, "loops.xml")
    add = _write(tmp_path / "auto.add.xml", xml)
    specs = user_detectors(_inputs(net_file, adds=[add]), read_net(net_file))
    assert [(s.id, s.lane_id, s.pos_m, s.period_s) for s in specs] == [
        ("auto_e0_0_0", "e0_0", 100.0, 60.0),
        ("auto_e0_0_1", "e0_0", 350.0, 60.0),
        ("auto_e2_2_0", "e2_2", 12.5, 60.0),
    ]


@pytest.mark.parametrize("name", ["highway_bremen", "spreewaldring", "netgen_corridor"])
def test_example_scenarios_fit_their_networks(name: str) -> None:
    """The shipped example sections: files resolve, demand fits, edges connect in order."""
    toml = Path(__file__).parents[2] / "scenarios" / f"{name}.toml"
    table = tomllib.loads(toml.read_text())
    inputs = resolve_inputs(toml.parent / table["network"]["sumocfg"], None, [], [], str(toml))
    net = read_net(inputs.net_file)
    assert all(v.length_m > 0 for v in check_demand(inputs, net).values())
    edges = [net.getEdge(e) for e in table["section"]["edges"]]
    downstream = edges[1:] + edges[:1] if table["section"]["closed"] else edges[1:]
    pairs = zip(edges, downstream, strict=False)
    for up, down in pairs:
        assert down in up.getOutgoing(), (up.getID(), down.getID())
    assert sum(e.getLength() for e in edges) > 1500.0

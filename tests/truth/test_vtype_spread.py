"""Ground truths whose standing queues do not sit on SUMO's 7.5 m lattice
(``truth.vtype_spread``): the spread route file, and a red light's queue in real SUMO."""

from __future__ import annotations

import importlib.util
import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import sumo
from conftest import ROOT, one_phase_program

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.demand import check_demand
from macromicro_sumo.sumo.inputs import SumoInputs, read_net, scenario_inputs
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.vtype_spread import MEMBER_SEP, SPREAD_MEMBERS, spread_routes

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
EDGES = ["1fi", "1si", "2o", "2fo"]
N_CARS = 14


def routes_file(folder: Path) -> Path:
    """``N_CARS`` cars of vType ``car`` (SUMO's passenger defaults: 5 m, 2.5 m) departing
    every 2 s at 10 m/s from 1fi to 2fo, and a truck type no vehicle uses."""
    path = folder / "r.rou.xml"
    cars = "".join(
        f'<vehicle id="v{i:02d}" type="car" depart="{2 * i}" departSpeed="10" '
        f'departLane="best"><route edges="{" ".join(EDGES)}"/></vehicle>\n'
        for i in range(N_CARS)
    )
    path.write_text(
        '<routes>\n<vType id="car" accel="2.6" decel="4.5"><param key="k" value="1"/></vType>\n'
        f'<vType id="truck" vClass="truck" length="12" minGap="3"/>\n{cars}</routes>\n'
    )
    return path


def test_each_vtype_becomes_a_seeded_distribution_of_the_same_mean(tmp_path: Path) -> None:
    """Every vType becomes a distribution of its id with ``SPREAD_MEMBERS`` members that keep
    its other attributes and children, whose mean length and minGap are the vType's (SUMO's
    vClass default where it sets none); the same seed writes the same bytes, another seed
    other members; the vehicles are untouched."""
    src = routes_file(tmp_path)
    a = spread_routes(src, tmp_path / "a.rou.xml", 3)
    b = spread_routes(src, tmp_path / "b.rou.xml", 3)
    c = spread_routes(src, tmp_path / "c.rou.xml", 4)
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()
    root = ET.parse(a).getroot()
    dists = {d.get("id"): list(d) for d in root.iter("vTypeDistribution")}
    assert set(dists) == {"car", "truck"}
    assert not [e for e in root if e.tag == "vType"]
    for vid, (length, gap) in {"car": (5.0, 2.5), "truck": (12.0, 3.0)}.items():
        members = dists[vid]
        assert len(members) == SPREAD_MEMBERS
        assert members[0].get("id") == f"{vid}{MEMBER_SEP}00"
        lengths = np.array([float(m.get("length")) for m in members])
        gaps = np.array([float(m.get("minGap")) for m in members])
        assert abs(lengths.mean() - length) < 0.01 and abs(gaps.mean() - gap) < 0.02
        assert lengths.std() > 0.05 * length and gaps.std() > 0.2
        assert lengths.min() > 0.7 * length and gaps.min() >= 1.0
    car = dists["car"][0]
    assert car.get("accel") == "2.6" and car.find("param").get("value") == "1"
    assert len(root.findall("vehicle")) == N_CARS
    with pytest.raises(UserError, match="members = 1; accepted: at least 2"):
        spread_routes(src, tmp_path / "d.rou.xml", 3, members=1)


def standing_queue(folder: Path, routes: Path) -> tuple[list[tuple[float, str]], Simulation]:
    """The cars' (front position on 1si, vType) once they stand at signal 0, red all along,
    front first."""
    red = one_phase_program(folder, "0", "r" * 12)
    sim = Simulation(SumoOptions(CROSS, (red,), 0.5, 5, route_files=(routes,), user_demand=True))
    for _ in range(240):
        sim.step()
    st = sim.vehicle_states()
    queue = [
        (float(st.pos_m[i]), sim.vehicle_type(v))
        for i, v in enumerate(st.ids)
        if st.lanes[i].startswith("1si") and st.speed_mps[i] < 0.1
    ]
    return sorted(queue, reverse=True), sim


def test_a_red_lights_queue_stands_off_the_lattice(tmp_path: Path) -> None:
    """A red light's queue of equal cars stands on SUMO's lattice: every front 7.5 m (5 m car
    and 2.5 m minGap) behind the next. With the vTypes spread each front stands its
    leader's length and its own minGap behind, so the spacings spread (at least 5 distinct,
    some 0.5 m off 7.5) and so do the fronts' places modulo 7.5 m. The cars drive as the
    members SUMO drew, the members ``check_demand`` returns."""
    plain = routes_file(tmp_path)
    queue, sim = standing_queue(tmp_path, plain)
    sim.close()
    assert len(queue) >= 10
    steps = -np.diff([p for p, _ in queue])
    assert np.allclose(steps, 7.5, atol=0.01), steps
    spread = spread_routes(plain, tmp_path / "spread.rou.xml", 11)
    queue, sim = standing_queue(tmp_path, spread)
    try:
        shapes = {t: sim.vtype_shape(t)[:2] for _, t in queue}
    finally:
        sim.close()
    assert len(queue) >= 10
    assert all(t.startswith(f"car{MEMBER_SEP}") for _, t in queue)
    steps = -np.diff([p for p, _ in queue])
    want = [
        shapes[a][0] + shapes[b][1] for (_, a), (_, b) in zip(queue[:-1], queue[1:], strict=True)
    ]
    assert np.allclose(steps, want, atol=0.01), (steps, want)
    assert len(np.unique(np.round(steps, 2))) >= 5 and np.abs(steps - 7.5).max() > 0.5
    phase = np.mod(queue[0][0] - np.array([p for p, _ in queue]), 7.5)
    assert np.ptp(phase) > 1.0, phase
    used = check_demand(SumoInputs(CROSS, (spread,), (), None), read_net(CROSS))
    assert {t for _, t in queue} <= set(used)
    assert "car" not in used and len(used) == SPREAD_MEMBERS


def _script(name: str):
    """A script of scripts/ as a module (they import each other by name)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_bench_arterial_and_a_scenario_copy_spread_their_vtypes(tmp_path: Path) -> None:
    """``bench_arterial.arterial(..., spread=True)`` writes its car and truck vTypes as
    distributions drawn from its seed (the same folder twice: the same file);
    ``spread_scenario.py`` copies a scenario with its route files spread, every network path
    absolute, and the copy loads with the members as its demand's vTypes."""
    bench = _script("bench_hidden_count")
    table, desc = bench.arterial(tmp_path, 801, bench.netconvert, spread=True)
    routes = Path(table["network"]["route_files"][0])
    first = routes.read_bytes()
    assert desc.endswith(", vTypes spread")
    dists = {d.get("id") for d in ET.parse(routes).getroot().iter("vTypeDistribution")}
    assert dists == {"car", "truck"}
    bench.arterial(tmp_path, 801, bench.netconvert, spread=True)
    assert routes.read_bytes() == first
    plain = tmp_path / "plain"
    plain.mkdir()
    table, _ = bench.arterial(plain, 801, bench.netconvert)
    toml = plain / "s.toml"
    net = Path(table["network"]["net_file"])
    toml.write_text(
        f'name = "a"\nseed = 801\n[network]\nkind = "sumo"\nnet_file = "{net.name}"\n'
        f'route_files = ["art.rou.xml"]\n[section]\nedges = {json.dumps(table["section"]["edges"])}\n'
    )
    script = _script("spread_scenario")
    copy = script.spread_scenario(toml, tmp_path / "copy", None, 5)
    sc = load_scenario(copy)
    inputs = scenario_inputs(sc)
    assert inputs.net_file == net.resolve()
    assert inputs.route_files == (tmp_path / "copy" / "spread_0_art.rou.xml",)
    used = check_demand(inputs, read_net(inputs.net_file))
    assert len(used) == 2 * 5 and all(MEMBER_SEP in v for v in used)

"""A ring file read as a section scenario (scenario/ring_as_section.py): how every ring file
loads since stop 25."""

from __future__ import annotations

import dataclasses
import tomllib
import xml.etree.ElementTree as ET

import pytest
from conftest import NETS, ROOT

from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.ring_as_section import RING_GENERATOR_DEFAULTS, detector_file
from macromicro_sumo.scenario.section import SectionGeneratorConfig, SectionScenario

SCENARIOS = ROOT / "scenarios"
RING_FILES = ["ring_paper", "ring_paper_strict", "ring_sweep", "ring_sugiyama"]
SECTION: dict = {}  # no key needed: a ring file is a section


def _mapped(name: str) -> SectionScenario:
    return load_scenario(SCENARIOS / f"{name}.toml", SECTION, allow_sweep=True)


def test_ring_paper_maps_to_ring_paper_section_in_every_field_but_its_name():
    mapped = _mapped("ring_paper")
    spelled = load_scenario(SCENARIOS / "ring_paper_section.toml")
    assert isinstance(mapped, SectionScenario)
    assert mapped.name == "ring_paper" != spelled.name
    assert dataclasses.replace(mapped, name=spelled.name) == spelled
    assert mapped.to_dict() | {"name": spelled.name} == spelled.to_dict()


@pytest.mark.parametrize("name", RING_FILES)
def test_every_ring_file_loads_as_a_section_with_its_settings(name):
    raw = tomllib.loads((SCENARIOS / f"{name}.toml").read_text())
    sec = _mapped(name)
    assert isinstance(sec, SectionScenario)
    assert sec.section.closed and len(sec.section.edges) == raw["network"].get("n_edges", 4)
    net = (SCENARIOS / raw["network"]["net_file"]).resolve()
    assert sec.resolve(sec.network.net_file) == net
    assert sec.network.route_files == [] and len(sec.network.additional_files) == 1
    assert sec.fleet.n_vehicles == raw["fleet"]["n_vehicles"]
    assert sec.speed_limits.range_mps == tuple(raw["speed_limits"]["range_mps"])
    assert sec.seed == raw["seed"] and sec.simulation.warmup_s == 0.0
    for key in ("step_length_s", "duration_s", "n_runs"):
        assert getattr(sec.simulation, key) == raw["simulation"].get(key, 0.5)
    assert sec.detectors.use_user
    assert sec.bounds.accel_mps2 == tuple(raw["bounds"]["accel_mps2"])
    assert sec.bounds.min_gap_m == raw["fleet"]["min_gap_m"][0]
    for key, value in raw["generator"].items():  # every generator key reads as written
        if key not in ("lambda_rec", "psi_source"):  # 0 and "detectors": the section's own
            got = getattr(sec.generator, key)
            assert got == (tuple(value) if isinstance(value, list) else value), key
    for key, default in RING_GENERATOR_DEFAULTS.items():  # ... and the ring's defaults
        assert getattr(sec.generator, key) == raw["generator"].get(key, default), key
    assert sec.generator.k_source == "truth" and sec.instrumented.hidden == "snapshot"
    completions = raw.get("evaluation", {}).get("completions_per_scene", 1)
    assert sec.generator.eval_completions == completions


def test_a_section_file_loads_the_same_with_road_section():
    path = SCENARIOS / "ring_two_lane.toml"
    assert load_scenario(path, SECTION) == load_scenario(path)
    with pytest.raises(UserError, match="road = 'ring' was removed"):
        load_scenario(path, {"road": "ring"})


def test_the_ring_generator_defaults_differ_from_the_sections():
    sec = {f.name: f.default for f in dataclasses.fields(SectionGeneratorConfig)}
    assert all(k in sec and sec[k] != v for k, v in RING_GENERATOR_DEFAULTS.items())


@pytest.mark.parametrize(
    "overrides, drop, says",
    [
        ({"generator.lambda_rec": 0.1}, (), "generator.lambda_rec = 0.1 has no section meaning"),
        ({"generator.psi_source": "trajectories"}, (), "generator.psi_source = 'trajectories'"),
        ({"generator.bounds_source": "fixed"}, (), "accepted 'extended' or remove the key"),
        ({"detectors.e1_position": 0.3}, (), "detectors.e1_position = 0.3 has no section"),
        ({"network.radius_m": 90.0}, (), "accepted radius_m = 100.0000"),
        ({"network.n_edges": 5}, (), "names edge e4"),
        ({"network.lanes": 2}, (), "unknown key [network] 'lanes'"),
        ({"road": "sections"}, (), "road = 'sections' is not accepted"),
        ({}, ("network.radius_m",), "missing required key 'network.radius_m'"),
        ({}, ("fleet",), "missing required table [fleet]"),
    ],
)
def test_a_ring_key_without_section_meaning_is_a_one_line_error(
    make_scenario, overrides, drop, says
):
    path = make_scenario({**SECTION, **overrides}, drop=drop)
    with pytest.raises(UserError) as err:
        load_scenario(path)
    assert says in str(err.value) and str(path) in str(err.value)
    assert "\n" not in str(err.value)


def test_a_net_without_the_rings_detector_file_is_named(tmp_path, make_scenario):
    net = tmp_path / "ring.net.xml"
    net.write_text((NETS / "ring_r100_e4.net.xml").read_text())
    path = make_scenario({**SECTION, "network.net_file": str(net)})
    with pytest.raises(UserError, match=r"has no ring detector file .*ring\.det\.add\.xml"):
        load_scenario(path)


def _loops(xml: str) -> set[tuple[str, str, float, float]]:
    """(kind, lane, from, to) of every E1 and E2 of an additional file's text."""
    out = set()
    for e in ET.fromstring(xml):
        if e.tag == "inductionLoop":
            out.add(("e1", e.get("lane"), round(float(e.get("pos")), 4), 0.0))
        elif e.tag == "laneAreaDetector":
            out.add(("e2", e.get("lane"), float(e.get("pos")), round(float(e.get("endPos")), 4)))
    return out


@pytest.mark.parametrize("net", ["ring_r100_e4.net.xml", "ring_r36.6_e4.net.xml"])
def test_the_shipped_detector_files_place_the_ring_truths_loops(net):
    """The section reads the ring's detectors from the file beside its net: an E1 loop at
    mid-edge and an E2 over every edge (as the ring wing's truth wrote them per run)."""
    geo = read_section(NETS / net, ["e0", "e1", "e2", "e3"], closed=True)
    edges = list(zip([ids[0] for ids in geo.edge_lane_ids], geo.lengths_m, strict=True))
    ring = {("e1", lane, round(0.5 * length, 4), 0.0) for lane, length in edges}
    ring |= {("e2", lane, 0.0, round(length, 4)) for lane, length in edges}
    shipped = _loops((NETS / detector_file(net)).read_text())
    assert len(shipped) == 2 * len(geo.edge_ids) and shipped == ring


def test_section_keys_in_the_ring_tables_override_the_mapping(make_scenario):
    sc = load_scenario(
        make_scenario(
            {**SECTION, "simulation.warmup_s": 30.0, "generator.dispersion_error": "absolute"}
        )
    )
    assert sc.simulation.warmup_s == 30.0 and sc.generator.dispersion_error == "absolute"
    with pytest.raises(UserError, match="unknown key 'instrumented' in a ring file"):
        load_scenario(make_scenario({**SECTION, "instrumented.penetration": 1.0}))

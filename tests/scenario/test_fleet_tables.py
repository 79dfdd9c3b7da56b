"""The fleet tables ([fleet], [speed_limits], [initial]): one definition for the ring and
sections, optional on a section, and ring_paper_section.toml's demand is ring_paper's."""

from __future__ import annotations

import pytest
from conftest import PAPER_SCENARIO, ROOT

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario import section
from macromicro_sumo.scenario.fleet import fleet_demand
from macromicro_sumo.scenario.load import load_scenario

RING_AS_SECTION = ROOT / "scenarios" / "ring_paper_section.toml"
TWO_LANE = ROOT / "scenarios" / "ring_two_lane.toml"


def test_sections_have_the_fleet_dataclasses():
    assert section.SectionScenario.__dataclass_fields__["fleet"].type is not None
    hints = section.SectionScenario.__dataclass_fields__
    assert {"fleet", "speed_limits", "initial"} <= set(hints)


def test_ring_paper_section_draws_the_demand_of_ring_paper():
    paper, sec = load_scenario(PAPER_SCENARIO), load_scenario(RING_AS_SECTION)
    assert isinstance(sec, section.SectionScenario)
    assert fleet_demand(sec) == fleet_demand(paper)
    assert sec.seed == paper.seed
    assert sec.simulation.step_length_s == paper.simulation.step_length_s
    assert sec.simulation.duration_s == paper.simulation.duration_s
    assert sec.simulation.n_runs == paper.simulation.n_runs
    assert sec.resolve(sec.network.net_file) == paper.resolve(paper.network.net_file)


def test_a_section_without_a_fleet_keeps_its_dict():
    plain = load_scenario(TWO_LANE)
    assert fleet_demand(plain) is None
    assert not {"fleet", "speed_limits", "initial"} & set(plain.to_dict())


def test_a_fleet_table_with_a_bad_value_names_its_key(tmp_path):
    text = RING_AS_SECTION.read_text().replace("n_vehicles = 5", "n_vehicles = 1")
    path = tmp_path / "s.toml"
    path.write_text(text.replace('"../sumo_nets/', f'"{ROOT}/sumo_nets/'))
    with pytest.raises(UserError, match=r"fleet\.n_vehicles = 1 is out of range"):
        load_scenario(path)

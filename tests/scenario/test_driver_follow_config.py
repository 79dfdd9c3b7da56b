"""``policy.driver_follow``: "none" by default and left out of the scenario's dict there
(every existing scenario keeps its digest, so no stage reruns), "drawn" and "auto" only
with the Krauss prior (or "auto"), anything else a one-line error naming the file, the
field and what is accepted."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import small_section_scenario
from red_light import CROSS, EDGES

from macromicro_sumo.errors import UserError


def scenario(folder: Path, **policy):
    routes = folder / "r.rou.xml"
    routes.write_text('<routes>\n    <vehicle id="probe" depart="0"><route edges="'
                      + " ".join(EDGES) + '"/></vehicle>\n</routes>\n')  # fmt: skip
    return small_section_scenario(
        folder, CROSS, routes, EDGES, policy={"observation": "lookahead", **policy}
    )


def test_the_default_keeps_the_digest(tmp_path: Path) -> None:
    plain = scenario(tmp_path, prior="krauss")
    assert plain.policy.driver_follow == "none"
    assert "driver_follow" not in plain.to_dict()["policy"]
    said = scenario(tmp_path, prior="krauss", driver_follow="none")
    assert said.digest() == plain.digest()
    drawn = scenario(tmp_path, prior="krauss", driver_follow="drawn")
    assert drawn.policy.driver_follow == "drawn" and drawn.digest() != plain.digest()
    assert scenario(tmp_path, prior="auto", driver_follow="auto").policy.driver_follow == "auto"
    by = scenario(tmp_path, prior="krauss", driver_follow="by_vtype")
    assert by.policy.driver_follow == "by_vtype" and by.digest() != drawn.digest()


def test_an_unknown_value_is_one_line_naming_file_field_and_choices(tmp_path: Path) -> None:
    with pytest.raises(UserError) as err:
        scenario(tmp_path, prior="krauss", driver_follow="sometimes")
    msg = str(err.value)
    assert "\n" not in msg and "s.toml" in msg and "policy.driver_follow" in msg
    assert "'none', 'drawn', 'auto'" in msg


@pytest.mark.parametrize("prior", ["none", "idm", "gipps"])
def test_per_driver_taus_need_the_krauss_prior(tmp_path: Path, prior: str) -> None:
    with pytest.raises(UserError) as err:
        scenario(tmp_path, prior=prior, driver_follow="drawn")
    msg = str(err.value)
    assert "\n" not in msg and "s.toml" in msg and "policy.driver_follow" in msg
    assert "krauss" in msg and "accepted" in msg


def test_the_priors_choice_does_not_read_it(tmp_path: Path) -> None:
    """The prior's family and relaxation are chosen before the drivers' taus, with one tau:
    a choice made without per-driver taus stays valid with them (no choice again)."""
    from macromicro_sumo.policy.chosen_prior import choice_settings

    plain = scenario(tmp_path, prior="krauss").to_dict()
    drawn = scenario(tmp_path, prior="krauss", driver_follow="drawn").to_dict()
    assert choice_settings(drawn) == choice_settings(plain)

"""``deploy.merge_reach`` left at its default under ``deploy.merge`` "none" or "handover"
loads as "plain", what the driver does there, so the scenario a run records (its manifest's
``scenario``) says what runs; "occupation" set with them stays refused."""

from __future__ import annotations

import pytest
from conftest import PAPER_SCENARIO

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.load import load_scenario


@pytest.mark.parametrize("merge", ["none", "handover"])
def test_default_reach_is_plain_without_merge_sumo(merge: str) -> None:
    sc = load_scenario(PAPER_SCENARIO, {"deploy.merge": merge})
    assert sc.deploy.merge_reach == "plain"
    # Recorded as before stop 46 (plain is the omitted value): the digest of plain said.
    assert "merge_reach" not in sc.to_dict()["deploy"]
    said = load_scenario(PAPER_SCENARIO, {"deploy.merge": merge, "deploy.merge_reach": "plain"})
    assert said.digest() == sc.digest()
    with pytest.raises(UserError) as err:
        load_scenario(PAPER_SCENARIO, {"deploy.merge": merge, "deploy.merge_reach": "occupation"})
    msg = str(err.value)
    assert "\n" not in msg and "ring_paper.toml" in msg and "deploy.merge_reach" in msg, msg
    assert f"accepted with deploy.merge = {merge!r}: 'plain'" in msg, msg


def test_default_reach_stays_occupation_with_merge_sumo() -> None:
    """merge "sumo" (the default), said or not: the default occupation, recorded."""
    for overrides in ({}, {"deploy.merge": "sumo"}):
        sc = load_scenario(PAPER_SCENARIO, overrides)
        assert sc.deploy.merge_reach == "occupation"
        assert sc.to_dict()["deploy"]["merge_reach"] == "occupation"
    assert load_scenario(PAPER_SCENARIO, {"deploy.merge": "sumo"}).digest() == (
        load_scenario(PAPER_SCENARIO).digest()
    )

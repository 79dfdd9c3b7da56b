"""``detectors.near_line_queue`` (opt-in): a section scenario that does not set it keeps its
digest; set, it reaches the field data's hidden count (``truth.files``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.load import load_scenario

CORRIDOR = Path(__file__).resolve().parents[2] / "scenarios" / "netgen_corridor.toml"


def test_near_line_queue_is_off_and_left_out_of_the_digest_unless_set() -> None:
    sc = load_scenario(CORRIDOR)
    assert sc.detectors.near_line_queue is False
    assert "near_line_queue" not in sc.to_dict()["detectors"]
    on = load_scenario(CORRIDOR, {"detectors.near_line_queue": True})
    assert on.detectors.near_line_queue is True
    assert on.to_dict()["detectors"]["near_line_queue"] is True
    assert on.digest() != sc.digest()
    with pytest.raises(UserError, match="near_line_queue"):
        load_scenario(CORRIDOR, {"detectors.near_line_queue": "yes"})

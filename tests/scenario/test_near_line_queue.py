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


@pytest.mark.parametrize("word", ["all", "station"])
def test_near_line_queue_takes_the_share_words(word: str) -> None:
    """ "all" and "station" (``truth.standing.near_line_share``) are accepted, recorded and
    digested apart from true; anything else names every accepted value."""
    sc = load_scenario(CORRIDOR, {"detectors.near_line_queue": word})
    assert sc.detectors.near_line_queue == word
    assert sc.to_dict()["detectors"]["near_line_queue"] == word
    on = load_scenario(CORRIDOR, {"detectors.near_line_queue": True})
    assert sc.digest() != on.digest()
    accepted = 'accepted: true, false, "all" or "station"'
    with pytest.raises(UserError, match=accepted):
        load_scenario(CORRIDOR, {"detectors.near_line_queue": "stations"})
    with pytest.raises(UserError, match='must be true, false, "all" or "station"'):
        load_scenario(CORRIDOR, {"detectors.near_line_queue": 1})

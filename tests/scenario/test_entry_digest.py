"""``policy.driver_entry`` is read only where ``policy.driver_speed = "memory"``
(``env.driver_speed.driver_entry``: "queued" elsewhere), so it enters the scenario's dict,
digest and stage settings only there (``spec(..., omit_unless=...)``): a ring or a "drawn"
run made before the default moved (stop 47: "queued" -> "auto") keeps its digest and is not
retrained, while a "memory" run trained under "queued" still is."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import PAPER_SCENARIO, ROOT

from macromicro_sumo.pipeline.schedule import Stage, stage_settings
from macromicro_sumo.scenario.load import load_scenario

NETGEN = ROOT / "scenarios" / "netgen_corridor.toml"  # driver_speed = "memory"


def _changed(before: dict, after: dict, tmp_path: Path) -> set[str]:
    """The keys a stage reading every key (the policy's, strictest) redoes on."""
    stage = Stage("policy", tmp_path / "manifest.json", run=lambda: None)
    have, want = stage_settings(before, stage), stage_settings(after, stage)
    return {k for k in have.keys() | want.keys() if have.get(k) != want.get(k)}


@pytest.mark.parametrize("speed", ["none", "drawn"])
def test_where_nobody_reads_the_entry_it_is_left_out(tmp_path: Path, speed: str) -> None:
    sc = load_scenario(PAPER_SCENARIO, {"policy.driver_speed": speed})
    assert sc.policy.driver_entry == "auto"  # the default, unread here
    assert "driver_entry" not in sc.to_dict()["policy"]
    # Whatever the entry says, the same digest: that of a run recorded before the key moved
    # ("queued", left out as the old default), so its stages are done.
    for entry in ("queued", "held", "auto"):
        said = load_scenario(
            PAPER_SCENARIO, {"policy.driver_speed": speed, "policy.driver_entry": entry}
        )
        assert said.digest() == sc.digest(), entry
        assert not _changed(said.to_dict(), sc.to_dict(), tmp_path)


def test_the_paper_ring_keeps_its_digest_from_before_the_default_moved(tmp_path: Path) -> None:
    """ring_paper (no driver_speed): its policy stage recorded no driver_entry before stop 47
    and records none now: nothing to redo."""
    sc = load_scenario(PAPER_SCENARIO)
    before = load_scenario(PAPER_SCENARIO, {"policy.driver_entry": "queued"})
    assert sc.policy.driver_speed == "none"
    assert "driver_entry" not in sc.to_dict()["policy"]
    assert sc.digest() == before.digest()
    assert not _changed(before.to_dict(), sc.to_dict(), tmp_path)


def test_a_memory_run_trained_under_queued_is_retrained(tmp_path: Path) -> None:
    sc = load_scenario(NETGEN)
    assert sc.policy.driver_speed == "memory"
    assert sc.to_dict()["policy"]["driver_entry"] == "auto"
    queued = load_scenario(NETGEN, {"policy.driver_entry": "queued"})
    held = load_scenario(NETGEN, {"policy.driver_entry": "held"})
    assert "driver_entry" not in queued.to_dict()["policy"]  # the old default, as recorded
    assert len({sc.digest(), queued.digest(), held.digest()}) == 3
    assert _changed(queued.to_dict(), sc.to_dict(), tmp_path) == {"policy.driver_entry"}
    assert _changed(held.to_dict(), sc.to_dict(), tmp_path) == {"policy.driver_entry"}

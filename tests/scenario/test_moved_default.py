"""A key whose default moved (``spec(..., omit_value=...)``): a scenario that does not set it
records the new default, so a stage done under the old default is redone, while one that
sets the old value keeps the digest it had before the key existed."""

from __future__ import annotations

from pathlib import Path

from conftest import PAPER_SCENARIO

from macromicro_sumo.pipeline.schedule import Stage, stage_settings
from macromicro_sumo.scenario.load import load_scenario

# (key, default now, the value that does what the package did before the key existed)
MOVED = (
    ("command_brake", "decel", "bounds"),
    ("actor_dtype", "float32", "float64"),
    ("turns", "handover", "off"),
    ("yellow", "ahead", "stop"),
    ("turn_gap", "sumo", "off"),
    ("merge_reach", "occupation", "plain"),
    ("command_dawdle", "signals", 0.0),
    ("start_dawdle", 0.5, 0.0),
    ("start_reaction_s", 1.0, 0.0),
    ("start_rules", "signal_lanes", "all"),
    ("keep_clear", "lane1", "off"),
    ("merge_follow", "last_lane", "off"),
    ("merge_follow_tolerance_mps", 0.5, 1.0),
)


def test_moved_defaults_are_recorded_and_their_old_values_left_out() -> None:
    sc = load_scenario(PAPER_SCENARIO)
    deploy = sc.to_dict()["deploy"]
    for key, now, old in MOVED:
        assert getattr(sc.deploy, key) == now and deploy[key] == now
        said_old = load_scenario(PAPER_SCENARIO, {f"deploy.{key}": old})
        assert key not in said_old.to_dict()["deploy"]
        assert said_old.digest() != sc.digest()
    # Keys whose default never moved stay out at their default (keep_right "off").
    assert "keep_right" not in deploy and sc.deploy.keep_right == "off"


def _redone(name: str, before: dict, now: dict, tmp_path: Path) -> tuple[Stage, dict, set[str]]:
    """Stage ``name``, its settings as ``before`` recorded them, and the keys whose recorded
    value differs from ``now``'s: what ``pipeline.schedule`` redoes the stage on."""
    stage = Stage(name, tmp_path / "manifest.json", run=lambda: None)
    have, want = stage_settings(before, stage), stage_settings(now, stage)
    return stage, have, {k for k in have.keys() | want.keys() if have.get(k) != want.get(k)}


def test_a_stage_recorded_before_the_default_moved_is_redone(tmp_path: Path) -> None:
    """The recorded scenario of a run deployed before (neither key: the old defaults) differs
    from today's in exactly the moved keys, which is what ``pipeline.schedule`` redoes on."""
    sc = load_scenario(PAPER_SCENARIO)
    before = sc.to_dict()
    for key, _, _ in MOVED:
        del before["deploy"][key]
    stage, have, changed = _redone("deploy", before, sc.to_dict(), tmp_path)
    assert changed == {f"deploy.{key}" for key, _, _ in MOVED}
    # A run that set the old values explicitly recorded none of them: nothing to redo.
    old = {f"deploy.{key}": value for key, _, value in MOVED}
    assert stage_settings(load_scenario(PAPER_SCENARIO, old).to_dict(), stage) == have


# policy keys whose default moved (key, default now, the value before): the policy stage is
# trained again where a run recorded none (stop 47: driver_entry "queued" -> "auto"; only
# where policy.driver_speed = "memory" reads it: tests/scenario/test_entry_digest.py)
POLICY_MOVED = (("driver_entry", "auto", "queued"),)
MEMORY = {"policy.driver_speed": "memory"}


def test_moved_policy_defaults_are_recorded_and_retrain(tmp_path: Path) -> None:
    sc = load_scenario(PAPER_SCENARIO, MEMORY)
    policy = sc.to_dict()["policy"]
    for key, now, old in POLICY_MOVED:
        assert getattr(sc.policy, key) == now and policy[key] == now
        said_old = load_scenario(PAPER_SCENARIO, {**MEMORY, f"policy.{key}": old})
        assert key not in said_old.to_dict()["policy"]
        assert said_old.digest() != sc.digest()
    before = sc.to_dict()
    for key, _, _ in POLICY_MOVED:
        del before["policy"][key]
    stage, have, changed = _redone("policy", before, sc.to_dict(), tmp_path)
    assert changed == {f"policy.{key}" for key, _, _ in POLICY_MOVED}
    old = {f"policy.{key}": value for key, _, value in POLICY_MOVED}
    said = load_scenario(PAPER_SCENARIO, {**MEMORY, **old}).to_dict()
    assert stage_settings(said, stage) == have

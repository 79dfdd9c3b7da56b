"""What the policy stage records of its own choices: ``policy.driver_entry = "auto"`` resolved
(the rule, the observed first sights it read, why). Real SUMO and real training: the platoon
road of ``test_memory_auto_entry`` (inserted at ``departSpeed="max"``: "auto" is "held"), a
generator of two epochs, one PPO update."""

from __future__ import annotations

import dataclasses
import json

import pytest
from test_memory_auto_entry import platoon_scenario

from macromicro_sumo.env.driver_speed import (
    ENTRY_AT_OWN_SHARE,
    MIN_HELD_SIGHTS,
    EntryChoice,
    entry_record,
    resolved_entry,
)
from macromicro_sumo.pipeline.stages import train_generator, train_policy
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section


def with_policy(sc, **changes):
    return dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, **changes))


@pytest.fixture(scope="module")
def platoon(tmp_path_factory: pytest.TempPathFactory):
    """The platoon road's truth (two runs: one trains, one is held out) and a generator."""
    folder = tmp_path_factory.mktemp("stage_records")
    sc = load_scenario(platoon_scenario(folder, "max"))
    sc = dataclasses.replace(
        sc,
        simulation=dataclasses.replace(sc.simulation, n_runs=3),
        generator=dataclasses.replace(sc.generator, epochs=2, snapshot_every_s=20.0),
    )
    sc = with_policy(sc, updates=1, episodes_per_update=4, horizon=4, driver_entry="auto")
    gt = simulate_section(sc, folder / "gt", progress=False)
    train_generator(sc, gt, folder / "gen", progress=False)
    return sc, gt, folder / "gen" / "generator.pt", folder


def test_the_entry_record_says_the_rule_and_why() -> None:
    n = MIN_HELD_SIGHTS + 2
    held = entry_record(EntryChoice("held", n, 0.7, 3, 1.0))
    assert (held["resolved"], held["held_sights"], held["held_at_own"]) == ("held", n, 0.7)
    assert held["why"].endswith(": held") and "free ones not" in held["why"]
    ins = entry_record(EntryChoice("insertion", n, 0.7, n, 0.8))
    assert ins["why"].endswith(": insertion") and ins["free_at_own"] == 0.8
    at = entry_record(EntryChoice("queued", n, ENTRY_AT_OWN_SHARE, 0, float("nan")))
    assert at["why"].endswith(": queued") and "not below" in at["why"]
    # no sight at all (or drivers that read no entry): NaN shares are JSON's null
    none = entry_record(EntryChoice("queued", 0, float("nan")))
    assert none["held_at_own"] is None and none["why"].startswith("no observed first sight")
    assert json.loads(json.dumps(none, allow_nan=False))["setting"] == "auto"


def test_the_manifest_records_what_auto_trained_with(platoon) -> None:
    sc, gt, gen, folder = platoon
    manifest = train_policy(sc, gt, gen, folder / "auto", progress=False)
    truth = load_section_truth(gt, sc)
    got = manifest["driver_entry"]
    # the train + val runs' observed drivers, as the stage's banks read them
    _, choice = resolved_entry(sc, truth, None)
    assert got == entry_record(choice) and got["resolved"] == "held"
    assert got["held_sights"] >= MIN_HELD_SIGHTS and got["held_at_own"] < ENTRY_AT_OWN_SHARE
    written = json.loads((folder / "auto" / "policy_manifest.json").read_text())
    assert written["driver_entry"] == got
    # a rule set explicitly is the scenario's own word: nothing resolved, nothing recorded
    explicit = with_policy(sc, driver_entry="held")
    assert "driver_entry" not in train_policy(explicit, gt, gen, folder / "held", progress=False)

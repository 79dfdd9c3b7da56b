"""``policy.relax_refit``: the sigma a fallen-back Krauss a's relaxation is refitted at
(``pipeline.build.relax_dawdle``), the deployment's command dawdle on the section: "dawdled"
reads ``deploy.command_dawdle`` and whether the truth recorded signals; "vtype" (the
default) never dawdles, so the fit is the one before the setting (docs/deploy-log.md, stop
51 hP51: drawn arterial 1706 0.983 -> 0.898 m/s retrained)."""

from __future__ import annotations

from types import SimpleNamespace

import pandas as pd

from macromicro_sumo.deploy.safety import AUTO_SIGMA
from macromicro_sumo.pipeline.build import relax_dawdle
from macromicro_sumo.scenario.load import load_scenario

SIGNALS = pd.DataFrame({"run": [0], "time_s": [0.0]})


def scenario(refit: str, dawdle):
    return SimpleNamespace(
        policy=SimpleNamespace(relax_refit=refit), deploy=SimpleNamespace(command_dawdle=dawdle)
    )


def test_dawdled_reads_the_deployments_command_dawdle_on_the_section():
    lights, none = SimpleNamespace(signals=SIGNALS), SimpleNamespace(signals=None)
    assert relax_dawdle(scenario("dawdled", "signals"), lights) == AUTO_SIGMA
    assert relax_dawdle(scenario("dawdled", "signals"), none) == 0.0
    assert relax_dawdle(scenario("dawdled", "signals"), SimpleNamespace()) == 0.0  # a ring
    assert relax_dawdle(scenario("dawdled", "auto"), none) == AUTO_SIGMA
    assert relax_dawdle(scenario("dawdled", 0.3), none) == 0.3
    assert relax_dawdle(scenario("dawdled", 0.0), lights) == 0.0
    for dawdle in ("signals", "auto", 0.3):
        assert relax_dawdle(scenario("vtype", dawdle), lights) == 0.0


def test_the_setting_is_a_policy_key_left_out_of_a_default_scenario(tmp_path):
    base = load_scenario("scenarios/highway_bremen.toml")
    assert base.policy.relax_refit == "vtype"
    assert "relax_refit" not in base.to_dict()["policy"]  # digests as before
    changed = load_scenario("scenarios/highway_bremen.toml", {"policy.relax_refit": "dawdled"})
    assert changed.policy.relax_refit == "dawdled"

"""The observation feature registry: one entry per feature, the PPO agent normalises by it."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from macromicro_sumo.env.observation import FEATURES, shift_scale
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.road.physics import OBSERVATION_FEATURES, OWN_FEATURES, SCENE_FEATURES
from macromicro_sumo.scenario.stages import PolicyConfig


def test_every_observed_feature_has_a_unit_and_a_scaling():
    for names in OBSERVATION_FEATURES.values():
        for name in names:
            f = FEATURES[name]
            assert f.name == name and f.unit in ("m", "m/s") and f.scale > 0


def test_the_ring_agent_normalises_with_the_registry():
    for observation in OBSERVATION_FEATURES:
        agent = Agent(observation=observation)
        shift, scale = shift_scale(observation)
        np.testing.assert_array_equal(agent.shift.numpy(), shift.astype(np.float32))
        np.testing.assert_array_equal(agent.scale.numpy(), scale.astype(np.float32))
        assert agent.shift.dtype == torch.float32


def test_the_scenario_accepts_every_registered_observation():
    """``policy.observation``'s choices are the registry's layouts (the scenario layer sits
    below road/ and cannot import it), each the scene's features then the vehicle's own."""
    spec = {f.name: f for f in dataclasses.fields(PolicyConfig)}["observation"]
    assert spec.metadata["choices"] == tuple(OBSERVATION_FEATURES)
    for names in OBSERVATION_FEATURES.values():
        own = [n for n in names if n in OWN_FEATURES]
        assert list(names[len(names) - len(own) :]) == own
        # The paper's four, the leader column the spacing or (a gap layout) the gap.
        paper = SCENE_FEATURES["paper"]
        assert names[:4] in (paper, (*paper[:2], "gap_m", paper[3]))

"""The observation feature registry: one entry per feature, the PPO agent normalises by it."""

from __future__ import annotations

import numpy as np
import torch

from macromicro_sumo.env.observation import FEATURES, OBS_SHIFT_SCALE, shift_scale
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.road.physics import OBSERVATION_FEATURES


def test_every_observed_feature_has_a_unit_and_a_scaling():
    for names in OBSERVATION_FEATURES.values():
        for name in names:
            f = FEATURES[name]
            assert f.name == name and f.unit in ("m", "m/s") and f.scale > 0
    assert {n: (f.shift, f.scale) for n, f in FEATURES.items()} == OBS_SHIFT_SCALE


def test_the_ring_agent_normalises_with_the_registry():
    for observation in OBSERVATION_FEATURES:
        agent = Agent(observation=observation)
        shift, scale = shift_scale(observation)
        np.testing.assert_array_equal(agent.shift.numpy(), shift.astype(np.float32))
        np.testing.assert_array_equal(agent.scale.numpy(), scale.astype(np.float32))
        assert agent.shift.dtype == torch.float32

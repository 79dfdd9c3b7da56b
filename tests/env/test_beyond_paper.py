"""The two documented departures from the paper, each against the paper's own setting."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SMALL_RING, write_scenario
from gymnasium.utils.env_checker import check_env
from loss_terms import spacing_losses

from macromicro_sumo.env.section_envs import SectionHiddenEnv
from macromicro_sumo.scenario.load import load_scenario


def test_l_var_measured_is_the_distance_to_the_target():
    gaps = np.array([[100.0, 150.0, 0.0]])
    mask = np.array([[True, True, False]])
    one = np.array([125.0])
    paper = spacing_losses(gaps, mask, one, one * 0.5, one * 2)["L_var"][0]
    measured = spacing_losses(gaps, mask, one, one * 0.5, one * 2, np.array([25.0]))["L_var"][0]
    assert paper == pytest.approx(25.0 / 125.0) and measured == pytest.approx(0.0)
    # Deviations count from the measured mean, not from A's own (112.5 m here).
    gaps = np.array([[100.0, 125.0, 0.0]])
    measured = spacing_losses(gaps, mask, one, one * 0.5, one * 2, np.array([10.0]))["L_var"][0]
    assert measured == pytest.approx(abs((25.0**2 + 0.0) / 2 - 10.0**2) / 125.0**2)


def test_l_var_measured_is_unbiased_for_the_few_gaps_one_vehicle_touches():
    """One placed vehicle touches two gaps: their spread around their own mean is half the
    stream's variance on average; around the measured mean it is the stream's."""
    rng = np.random.default_rng(0)
    gaps = rng.normal(125.0, 30.0, size=(20_000, 2))
    mask = np.ones_like(gaps, dtype=bool)
    mean = np.full(len(gaps), 125.0)
    zero = np.zeros(len(gaps))
    # L_var = |var_A - target^2| / mean^2 with target 0 gives var_A itself.
    var_a = spacing_losses(gaps, mask, mean, mean * 0.1, mean * 10, zero)["L_var"] * 125.0**2
    own_mean = gaps.var(axis=1)
    assert var_a.mean() == pytest.approx(900.0, rel=0.03)
    assert own_mean.mean() == pytest.approx(450.0, rel=0.03)


@pytest.mark.parametrize(("observation", "dim"), [("paper", 4), ("lookahead", 6)])
def test_both_observations_pass_the_gymnasium_checker(small_ring_gt, tmp_path, observation, dim):
    path = write_scenario(tmp_path, {**SMALL_RING, "policy.observation": observation})
    env = SectionHiddenEnv(load_scenario(path), small_ring_gt, None)
    try:
        check_env(env, skip_render_check=True)
        obs, _ = env.reset(seed=1)
        assert obs.shape == (dim,)
        if observation == "lookahead":  # the next edge's limit, and the distance to it
            limits = env.core.episode_section.limits_mps
            assert obs[4] in set(limits.ravel().tolist())
            assert 0 < obs[5] <= env.core.section.lengths_m.max()
    finally:
        env.close()

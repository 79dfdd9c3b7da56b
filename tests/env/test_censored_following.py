"""The Krauss prior's pairs on an open section whose drivers' ratios fell back: the drivers seen
only as lower bounds (they never cruised freely) give their following pairs too, not only the
few free cruisers theirs (``env.observed_drivers.censored_following_pairs``; real SUMO: game/ramp's
congested merge, where 23 of 249 observed vehicles cruised freely)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import game_ramp_truth

from macromicro_sumo.env.observed_drivers import (
    FREE_GAP_M,
    FREE_HEADWAY_S,
    MIN_OWN_PAIRS,
    censored_following_pairs,
    krauss_pairs,
    observed_drivers,
    own_speed_pairs,
)
from macromicro_sumo.evaluation.micro_data import micro_pairs
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ramp(tmp_path_factory: pytest.TempPathFactory):
    """game/ramp's main line, one run of 120 s after 300 s (a queue at the merge), half the
    vehicles observed (~8 s of SUMO)."""
    return game_ramp_truth(tmp_path_factory.mktemp("ramp_censored"), "memory")


def test_censored_drivers_following_pairs_join_the_fallback_fit(ramp):
    """The ratios fall back (few free cruisers): the Krauss form's pairs are the free cruisers'
    own pairs and every pair of a lower-bound driver with a leader near, its limits as
    recorded. Before, the free cruisers' pairs alone: a few, selected drivers' following."""
    sc, truth = ramp
    runs = truth.runs
    drivers = observed_drivers(sc, truth, runs)
    obs, accel = micro_pairs(sc, truth, runs)
    fit_obs, fit_accel, estimate = krauss_pairs(sc, truth, runs, obs, accel)
    assert estimate.fallback  # the premise
    own_obs, own_accel = own_speed_pairs(drivers, estimate.median)
    more_obs, more_accel = censored_following_pairs(drivers)
    assert len(more_accel) > len(own_accel) > 0  # most observed cars queue
    assert len(fit_accel) == len(own_accel) + len(more_accel)
    np.testing.assert_array_equal(fit_obs, np.concatenate([own_obs, more_obs]))
    np.testing.assert_array_equal(fit_accel, np.concatenate([own_accel, more_accel]))
    # each joined pair: a censored driver's, behind a near leader, its own limit
    assert (more_obs[:, 2] < more_obs[:, 0] * FREE_HEADWAY_S + FREE_GAP_M).all()
    censored = np.array([k in drivers.lower for k in drivers.keys])
    near = drivers.obs[:, 2] < drivers.obs[:, 0] * FREE_HEADWAY_S + FREE_GAP_M
    np.testing.assert_array_equal(more_obs, drivers.obs[censored & near])


def test_a_closed_sections_pairs_keep_their_own_drivers_only(tmp_path: Path):
    """ring_two_lane (closed; one run of 300 s, ~2 s of SUMO): its ratios fall back too, and
    its pairs stay the free cruisers' own over their own median (stop 31), or every observed
    pair where those are fewer than ``MIN_OWN_PAIRS``: no censored drivers' pairs join."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(sc, simulation=replace(sc.simulation, n_runs=1, duration_s=300.0))
    simulate_section(sc, tmp_path / "gt", progress=False)
    truth = load_section_truth(tmp_path / "gt", sc)
    runs = truth.runs
    obs, accel = micro_pairs(sc, truth, runs)
    fit_obs, fit_accel, estimate = krauss_pairs(sc, truth, runs, obs, accel, own_median=True)
    drivers = observed_drivers(sc, truth, runs)
    assert estimate.fallback and drivers.lower  # the premise: censored drivers there
    own_obs, own_accel = own_speed_pairs(drivers, estimate.pairs_median)
    want = (own_obs, own_accel) if len(own_accel) >= MIN_OWN_PAIRS else (obs, accel)
    np.testing.assert_array_equal(fit_accel, want[1])
    np.testing.assert_array_equal(fit_obs, want[0])

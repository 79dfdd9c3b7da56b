"""Evaluation against the stations (``evaluation.section.station_errors``, ``stations_row``):
what a field-data evaluation compares its rollouts with, checked on constructed rollouts."""

from __future__ import annotations

import numpy as np
import pytest

from macromicro_sumo.data.section import PSI_FIELDS
from macromicro_sumo.env.rollout import Rollouts
from macromicro_sumo.evaluation.section import STATIONS, station_errors, stations_row


def _psi(speed: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    psi = np.full((len(speed), len(PSI_FIELDS)), np.nan)
    psi[:, PSI_FIELDS.index("mean_speed_mps")] = speed
    psi[:, PSI_FIELDS.index("mean_spacing_m")] = spacing
    return psi


def _rollouts(speed: np.ndarray, spacing: np.ndarray) -> Rollouts:
    shape = speed.shape
    zeros = np.zeros(shape)
    return Rollouts(zeros, speed, spacing, zeros, zeros, np.zeros(shape[::2], bool), 0, 0)


def test_station_errors_pair_each_episode_with_its_interval():
    rng = np.random.default_rng(3)
    e, h, n = 40, 10, 6
    station_v = rng.uniform(20.0, 35.0, e)  # each scene's interval differs
    station_d = rng.uniform(40.0, 80.0, e)
    # Every episode 1.5 m/s faster than its own interval, spacings 10 % longer; a vehicle
    # slot off the road (NaN) counts for nothing.
    v = station_v[:, None, None] + 1.5 + rng.normal(0.0, 0.3, (e, h, n))
    d = station_d[:, None, None] * 1.1 * np.ones((e, h, n))
    v[:, :, -1] = np.nan
    d[:, :, -1] = np.nan
    out = station_errors(_rollouts(v, d), _psi(station_v, station_d), seed=0)
    assert out["station_speed_err_mps"] == pytest.approx(1.5, abs=0.05)
    assert out["station_speed_err_ci_lo_mps"] < 1.5 < out["station_speed_err_ci_hi_mps"]
    assert out["station_spacing_ratio"] == pytest.approx(1.1, rel=1e-9)
    # Shuffled intervals: the episode means no longer pair with theirs, the interval widens.
    shuffled = station_errors(_rollouts(v, d), _psi(station_v[::-1], station_d), seed=0)
    width = out["station_speed_err_ci_hi_mps"] - out["station_speed_err_ci_lo_mps"]
    wide = shuffled["station_speed_err_ci_hi_mps"] - shuffled["station_speed_err_ci_lo_mps"]
    assert wide > 5 * width


def test_the_stations_row_holds_their_means_only():
    row = stations_row(
        {"hidden_count": "estimated"}, _psi(np.array([30.0, 20.0]), np.array([50.0, 70.0]))
    )
    assert row["method"] == STATIONS
    assert row["mean_speed_mps"] == 25.0 and row["mean_spacing_m"] == 60.0
    assert "std_speed_mps" not in row  # stations measure no spread

"""The generator manifest's ``spread_slope``: how the scenes' spacing std follows psi's across
detector intervals (a completion that leans to the training runs' spread has a slope below
1: docs/design.md, "Spacing spread across seeds (stop 29)")."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from macromicro_sumo.generator.section_stage import spread_slope


def _metrics(psi_std: np.ndarray, scene_std: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame({"psi_std_spacing_m": psi_std, "std_spacing_m": scene_std})


def test_a_spread_that_follows_psi_has_slope_one_and_a_flat_one_zero() -> None:
    rng = np.random.default_rng(3)
    psi = np.repeat([15.0, 25.0, 40.0, 55.0], 50)  # 4 intervals, 50 scenes each
    # Scenes scatter around psi's std; the root mean variance per interval restores it.
    scene = psi * np.sqrt(rng.chisquare(8, psi.size) / 8)
    assert spread_slope(_metrics(psi, scene), "std_spacing_m") == pytest.approx(1.0, abs=0.1)
    flat = np.full(psi.size, 30.0)
    assert spread_slope(_metrics(psi, flat), "std_spacing_m") == pytest.approx(0.0, abs=1e-9)
    half = 15.0 + 0.5 * (psi - 15.0)
    assert spread_slope(_metrics(psi, half), "std_spacing_m") == pytest.approx(0.5, abs=1e-9)


def test_no_slope_from_fewer_than_three_intervals_or_without_psis_spread() -> None:
    two = _metrics(np.repeat([20.0, 40.0], 5), np.repeat([20.0, 40.0], 5))
    assert spread_slope(two, "std_spacing_m") is None
    unknown = _metrics(np.full(6, np.nan), np.arange(6.0))
    assert spread_slope(unknown, "std_spacing_m") is None

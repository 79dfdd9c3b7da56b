"""policy.prior = "krauss" on a closed section (real SUMO: ring_two_lane, IDM cars and Krauss
vans on the two-lane ring): where the drivers' ratios fall back, the speed factor is still
fitted, since nothing beyond a closed section holds the drivers back; on an open one it is
held at 1 (tests/policy/test_prior_krauss_fallback.py, game/ramp)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ring_two_lane(tmp_path_factory: pytest.TempPathFactory):
    """One run of 300 s after the 120 s warm-up (~2 s of SUMO)."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(sc, simulation=replace(sc.simulation, n_runs=1, duration_s=300.0))
    folder = tmp_path_factory.mktemp("r2l")
    simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(folder / "gt", sc)


def test_a_closed_section_fits_the_speed_factor_where_the_ratios_fall_back(ring_two_lane):
    """Few observed cars cruise freely on the ring, so the ratios fall back; the fitted speed
    factor stands all the same, below the IDM cars' speedFactor 1 (they cruise below their
    desired speed at the ring's gaps), and the record says why the ratios fell back."""
    sc, truth = ring_two_lane
    assert truth.section.closed
    prior, extra, _ = fit_residual_prior(sc, truth, np.array([0]))
    record = extra["prior"]
    assert record["driver_ratios"]["fallback"]  # the premise
    assert "speed_factor" not in record["fallback"] and "speed_factor" in record["fitted"]
    assert 0.85 < prior["speed_factor"] < 0.97

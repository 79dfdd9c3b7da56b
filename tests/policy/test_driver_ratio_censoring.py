"""Desired-speed ratios under censoring (``env.driver_speed_ratios.ratio_estimate``): a vehicle held
at its own maxSpeed or never cruising freely gives a lower bound, not a ratio; the ratios are
a Kaplan-Meier estimate over both; too few exact ones keep SUMO's default distribution, and
then the Krauss-form prior's speed factor is held at SUMO's too (real SUMO for the cap)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from section_files import routes_file, section_scenario, vtype
from test_prior_krauss import DT_S, KRAUSS, LENGTH_M, _pairs

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import netconvert  # noqa: E402

from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS
from macromicro_sumo.env.driver_speed_ratios import (
    DEFAULT_RATIOS,
    MIN_EXACT_RATIOS,
    ObservedDrivers,
    censored_quantiles,
    ratio_estimate,
)
from macromicro_sumo.env.observed_drivers import observed_drivers, speed_caps
from macromicro_sumo.evaluation.krauss_fit import fit_krauss, sumo_defaults  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402

LIMIT_MPS = 30.0
TRUCK_MAX_MPS = 22.0  # the truck's maxSpeed: 0.733 of the limit, whatever its driver wants


def _drivers(exact: list[float], lower: list[float]) -> ObservedDrivers:
    ratio = {(0, f"e{i}"): r for i, r in enumerate(exact)}
    bounds = {(0, f"l{i}"): r for i, r in enumerate(lower)}
    return ObservedDrivers(ratio, np.empty((0, 4)), np.empty(0), [], bounds)


def test_without_bounds_the_quantiles_are_the_ratios_own():
    x = np.random.default_rng(0).normal(1.0, 0.1, 57)
    plain = np.quantile(x, QUANTILE_LEVELS, method="hazen")
    assert np.allclose(censored_quantiles(x, np.empty(0)), plain)
    # A bound below every ratio says nothing new: each ratio gains the same weight.
    assert np.allclose(censored_quantiles(x, np.array([0.1, 0.2])), plain)


def test_a_lower_bound_moves_its_weight_to_the_ratios_above_it():
    """Kaplan-Meier by hand: ratios 1, 2, 3, 4 and a bound at 2.5. Product-limit masses 0.2,
    0.2, 0.3, 0.3 (the bound's fifth goes half to 3, half to 4): the median is past 2.5,
    where the bound taken as a ratio, or left out, would keep it at 2.5 or below."""
    q = censored_quantiles(np.array([1.0, 2.0, 3.0, 4.0]), np.array([2.5]))
    # Each ratio at the middle of its mass: 0.1, 0.3, 0.55, 0.85.
    pos = np.array([0.1, 0.3, 0.55, 0.85])
    assert np.allclose(q, np.interp(QUANTILE_LEVELS, pos, [1.0, 2.0, 3.0, 4.0]))
    assert np.interp(0.5, QUANTILE_LEVELS, q) == pytest.approx(2.8)
    plain = np.quantile([1.0, 2.0, 3.0, 4.0], 0.5, method="hazen")
    assert plain == 2.5 and np.quantile([1.0, 2.0, 2.5, 3.0, 4.0], 0.5, method="hazen") == 2.5
    # A bound above every ratio gives its weight to the largest (no extrapolation).
    top = censored_quantiles(np.array([1.0, 2.0, 3.0]), np.array([5.0]))
    assert top[0] == 1.0 and top[-1] == 3.0
    assert np.interp(0.5, QUANTILE_LEVELS, top) > 2.0


def test_too_few_exact_ratios_keep_sumos_default_distribution():
    rng = np.random.default_rng(1)
    few = ratio_estimate(_drivers(list(rng.uniform(0.5, 0.8, MIN_EXACT_RATIOS - 1)), [0.4]))
    assert np.array_equal(few.quantiles, DEFAULT_RATIOS)
    assert f"{MIN_EXACT_RATIOS - 1} observed vehicles" in few.fallback
    assert few.record()["fallback"] == few.fallback and few.record()["lower_bounds"] == 1
    # SUMO's passenger speedFactor: median 1, within two deviations of 0.1.
    assert few.median == pytest.approx(1.0)
    assert DEFAULT_RATIOS[0] == pytest.approx(0.8) and DEFAULT_RATIOS[-1] == pytest.approx(1.2)
    enough = ratio_estimate(_drivers(list(rng.uniform(0.5, 0.8, MIN_EXACT_RATIOS)), []))
    assert enough.fallback == "" and enough.median < 0.8


def test_a_far_slower_driver_is_taken_as_held_back():
    """One ratio of 0.2 among drivers at 0.9-1.1 (a driver waiting at a merge the free test
    does not see): a lower bound, so no deployed driver is drawn a roadblock's factor."""
    ratios = list(np.linspace(0.9, 1.1, 40))
    est = ratio_estimate(_drivers([*ratios, 0.2], []))
    assert est.exact == 40 and est.lower_bounds == 1
    assert est.quantiles[0] == pytest.approx(0.9)
    plain = censored_quantiles(np.array([*ratios, 0.2]), np.empty(0))
    assert plain[0] == pytest.approx(0.2)  # as an exact ratio it would set the slowest draw


def test_a_fixed_speed_factor_stays_at_the_default_and_says_why():
    """Pairs of drivers at speed factor 0.97: held at SUMO's 1.0 the speed factor is not
    fitted, the record gives the reason, and the rest is still fitted (a as the pairs
    show it, not a default)."""
    obs, accel = _pairs(6000, seed=1, spacing_m=(8.0, 60.0))
    fit = fit_krauss(obs, accel, LENGTH_M, DT_S, None, {"speed_factor": "no ratios"})
    assert fit.params.speed_factor == sumo_defaults().speed_factor
    assert fit.fallback["speed_factor"] == "no ratios" and "speed_factor" not in fit.fitted
    assert "accel_mps2" in fit.fitted
    assert fit.params.accel_mps2 == pytest.approx(KRAUSS.accel_mps2, abs=0.4)
    free = fit_krauss(obs, accel, LENGTH_M, DT_S)
    assert free.params.speed_factor == pytest.approx(KRAUSS.speed_factor, abs=0.01)
    assert fit.rmse_mps2 > free.rmse_mps2  # the held factor is the wrong one here


def capped_scenario(folder: Path) -> Path:
    """A two-lane road at 30 m/s: cars (speedFactor 1) on the left lane, trucks whose
    maxSpeed is 22 m/s (speedFactor 1 as well) on the right, sparse, every vehicle observed
    (cars on the right would not pass the trucks: SUMO forbids overtaking on the right)."""
    net = netconvert(
        folder,
        '<node id="a" x="0" y="0"/>\n<node id="b" x="2500" y="0"/>',
        f'<edge id="E" from="a" to="b" numLanes="2" speed="{LIMIT_MPS}"/>',
    )
    lc = {"lcStrategic": -1, "lcSpeedGain": 0, "lcKeepRight": 0, "lcCooperative": 0}
    flow = 'route="r" end="3600" period="10" departSpeed="20"'
    routes = routes_file(
        folder / "r.rou.xml",
        [vtype("car", length=5, minGap=2.5, speedFactor=1, speedDev=0, **lc),
         vtype("truck", length=12, minGap=2.5, speedFactor=1, speedDev=0,
               maxSpeed=TRUCK_MAX_MPS, **lc)],
        [f'<flow id="c" type="car" begin="0" departLane="1" {flow}/>',
         f'<flow id="t" type="truck" begin="5" departLane="0" {flow}/>'],
        ['<route id="r" edges="E"/>'],
    )  # fmt: skip
    return section_scenario(
        folder / "capped.toml",
        net,
        routes,
        ["E"],
        seed=3,
        penetration=1.0,
        simulation={"warmup_s": 120.0, "duration_s": 90.0, "n_runs": 1},
        detectors={"interval_s": 30.0, "auto_spacing_m": 1000.0},
        policy={"prior": "krauss", "driver_speed": "drawn"},
    )


def test_a_vehicle_at_its_own_max_speed_gives_a_lower_bound(tmp_path: Path):
    """The trucks cruise freely at their maxSpeed, 0.733 of the limit: that is the vehicle's
    cap, so their top is a lower bound of their drivers' ratio; the cars' tops are ratios
    (1.0). Pooled, as before, the trucks pulled the median ratio towards 0.73."""
    sc = load_scenario(capped_scenario(tmp_path))
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    assert speed_caps(sc, truth) == {"truck": TRUCK_MAX_MPS}
    drivers = observed_drivers(sc, truth, truth.runs)
    trucks = {k: r for k, r in drivers.lower.items() if k[1].startswith("t.")}
    cars = {k: r for k, r in drivers.ratio.items() if k[1].startswith("c.")}
    assert len(trucks) >= 5 and len(cars) >= 5
    assert all(k[1].startswith("c.") for k in drivers.ratio)  # no truck has a ratio
    assert np.allclose(list(trucks.values()), TRUCK_MAX_MPS / LIMIT_MPS, atol=0.01)
    assert np.allclose(list(cars.values()), 1.0, atol=0.02)
    # Above every car ratio's smallest, the trucks' bounds go to the cars: median 1.0.
    q = censored_quantiles(np.array(list(drivers.ratio.values())), np.array(list(trucks.values())))
    assert np.interp(0.5, QUANTILE_LEVELS, q) == pytest.approx(1.0, abs=0.02)

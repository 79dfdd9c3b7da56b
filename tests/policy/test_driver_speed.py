"""Per-driver desired speeds (``policy.driver_speed``, ``env.driver_speed``): the observed
vehicles' free-flow ratios recover SUMO's speed factors, draws follow their distribution and
are the same for a vehicle whatever drives it, and a driver's factor moves only the limits
it observes, so the Gipps prior cruises at its own desired speed."""

from __future__ import annotations

import sys
from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import dump_toml

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import netconvert  # noqa: E402

from macromicro_sumo.deploy.observe import LaneTable, Table, observe_rows  # noqa: E402
from macromicro_sumo.env.driver_speed import (
    QUANTILE_LEVELS,
    DriverSpeeds,
    driver_levels,
    factors_at,
    ratio_quantiles,
    with_driver_factors,
)
from macromicro_sumo.env.observed_drivers import (
    MIN_OWN_PAIRS,
    free_speed_ratios,
    observed_drivers,
    own_speed_pairs,
    prior_pairs,
)
from macromicro_sumo.env.section_observations import section_observations  # noqa: E402
from macromicro_sumo.errors import UserError  # noqa: E402
from macromicro_sumo.policy.agent import Agent  # noqa: E402
from macromicro_sumo.policy.checkpoint import CHECKPOINT_FORMAT, load_checkpoint, signature  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.sumo.states import VehicleStates  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402

LIMIT_MPS = 30.0
FACTORS = (0.9, 1.1)  # the two vTypes' speedFactor (speedDev 0: exactly these)


@dataclass(frozen=True)
class Slots:
    """What ``with_driver_factors`` reads of a ``SectionBank``."""

    valid: np.ndarray
    hidden: np.ndarray
    driver_factor: np.ndarray | None = None


def straight_scenario(folder: Path, driver_speed: str = "none") -> Path:
    """A two-lane 3 km road at 30 m/s, a sparse flow of each of two vTypes with speed
    factors 0.9 and 1.1 on a lane of its own (no lane changes: a fast car would otherwise
    sit behind a slow one until it overtakes), every vehicle instrumented."""
    folder.mkdir(parents=True, exist_ok=True)
    net = netconvert(
        folder,
        '<node id="a" x="0" y="0"/>\n<node id="b" x="3000" y="0"/>',
        f'<edge id="E" from="a" to="b" numLanes="2" speed="{LIMIT_MPS}"/>',
    )
    types = "\n".join(
        f'    <vType id="f{i}" length="5" minGap="2.5" speedFactor="{f}" speedDev="0" '
        'lcStrategic="-1" lcSpeedGain="0" lcKeepRight="0" lcCooperative="0"/>'
        for i, f in enumerate(FACTORS)
    )
    flows = "\n".join(
        f'    <flow id="q{i}" type="f{i}" route="r" begin="{i * 6}" end="3600" period="12" '
        f'departSpeed="20" departLane="{i}"/>'
        for i in range(len(FACTORS))
    )
    routes = folder / "r.rou.xml"
    routes.write_text(f'<routes>\n{types}\n    <route id="r" edges="E"/>\n{flows}\n</routes>\n')
    table = {
        "name": "straight",
        "seed": 3,
        "network": {"kind": "sumo", "net_file": str(net), "route_files": [str(routes)]},
        "section": {"edges": ["E"]},
        "instrumented": {"penetration": 1.0},
        "simulation": {"warmup_s": 150.0, "duration_s": 120.0, "n_runs": 1},
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 1000.0},
        "policy": {"prior": "gipps", "driver_speed": driver_speed},
    }
    path = folder / "straight.toml"
    path.write_text(dump_toml(table))
    return path


@pytest.fixture(scope="module")
def straight(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("driver_speed")
    sc = load_scenario(straight_scenario(folder))
    gt = simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(gt, sc)


def test_free_speed_ratios_recover_sumos_speed_factors(straight) -> None:
    sc, truth = straight
    ratios = free_speed_ratios(sc, truth, truth.runs)
    # A vehicle every 6 s, each of them free at 20+ m/s (>= 120 m apart, 4 s at 30 m/s):
    # every vehicle that cruised long enough is one of the two factors, both kinds present.
    assert len(ratios) >= 10
    nearest = np.array(FACTORS)[np.argmin(np.abs(ratios[:, None] - np.array(FACTORS)), axis=1)]
    assert np.abs(ratios - nearest).max() < 0.02
    assert set(np.round(nearest, 1)) == set(FACTORS)


def test_own_speed_pairs_put_every_driver_at_the_median_drivers_desired_speed(straight) -> None:
    """Each observed vehicle's pairs carry its own factor in their limits: cruising, the
    0.9 and the 1.1 drivers alike then drive at one ratio of the scaled limit, the median
    driver's, which a shared model can fit (unscaled, they sit 0.2 apart)."""
    sc, truth = straight
    drivers = observed_drivers(sc, truth, truth.runs)
    obs, accel = own_speed_pairs(drivers)
    cruising = (obs[:, 2] > 200.0) & (np.abs(accel) < 0.3) & (obs[:, 0] > 26.0)
    assert cruising.sum() > 100
    median = np.median(list(drivers.ratio.values()))
    ratio = obs[cruising, 0] / obs[cruising, 1]
    assert np.quantile(np.abs(ratio - median), 0.95) < 0.02
    free = (drivers.obs[:, 2] > 200.0) & (np.abs(drivers.accel) < 0.3) & (drivers.obs[:, 0] > 26.0)
    raw = drivers.obs[free, 0] / drivers.obs[free, 1]
    assert np.quantile(raw, 0.95) - np.quantile(raw, 0.05) > 0.15
    # Only the "krauss" prior is fitted on them, and only where there are enough.
    assert len(accel) >= MIN_OWN_PAIRS
    krauss = replace(sc, policy=replace(sc.policy, prior="krauss"))
    fit_obs, _ = prior_pairs(krauss, truth, truth.runs, drivers.obs, drivers.accel)
    assert np.array_equal(fit_obs, obs)
    assert prior_pairs(sc, truth, truth.runs, drivers.obs, drivers.accel)[0] is drivers.obs


def test_draws_follow_the_ratios_and_are_fixed_per_vehicle() -> None:
    rng = np.random.default_rng(0)
    ratios = rng.normal(1.0, 0.1, 400)
    q = ratio_quantiles(ratios)
    assert q.shape == QUANTILE_LEVELS.shape and np.all(np.diff(q) >= 0)
    ids = [f"veh{i}" for i in range(4000)]
    f = factors_at(q, driver_levels(7, 0, ids))
    # Relative to the median: median 1, the ratios' spread (std 0.1 / median).
    assert abs(np.median(f) - 1.0) < 0.01
    assert abs(f.std() - ratios.std() / np.median(ratios)) < 0.01
    # Seeded by (seed, run, vehicle): the same again, another run another draw.
    assert np.array_equal(f, factors_at(q, driver_levels(7, 0, ids)))
    assert not np.allclose(f, factors_at(q, driver_levels(7, 1, ids)))
    sc = SimpleNamespace(seed=7, policy=SimpleNamespace(driver_speed="drawn"))
    drivers = DriverSpeeds(q, sc, 0)
    obs = np.zeros((5, 4))
    assert np.array_equal(drivers(ids[:5], obs), f[:5])
    assert np.array_equal(drivers(ids[3:1:-1], obs[:2]), f[3:1:-1])
    # No ratio measured: every driver the fitted prior's.
    assert np.all(factors_at(ratio_quantiles(np.empty(0)), np.array([0.1, 0.9])) == 1.0)


def test_memory_keeps_the_entry_ratio_within_the_observed_range() -> None:
    q = ratio_quantiles(np.linspace(0.8, 1.2, 41))  # median 1.0
    sc = SimpleNamespace(seed=7, policy=SimpleNamespace(driver_speed="memory", observation="paper"))
    drivers = DriverSpeeds(q, sc, 0)
    # Entering free at 27, 33 and 21 m/s on a 30 m/s road: 0.9, 1.1, and the slowest
    # observed ratio for the car that entered at 0.7 (a queued one, below 0.65, or a held
    # one is drawn: tests/policy/test_memory_queued_entry.py, test_memory_held_entry.py).
    first = np.array([[27.0, 30.0, 250.0, 0.0], [33.0, 30.0, 250.0, 0.0], [21.0, 30.0, 250.0, 0.0]])
    assert np.allclose(drivers(["a", "b", "c"], first), [0.9, 1.1, 0.8])
    # Kept while driven, whatever the speed now.
    assert np.allclose(drivers(["c", "a"], first[[0, 1]] * [2.0, 1.0, 1.0, 1.0]), [0.8, 0.9])


def test_the_factor_moves_only_the_observed_limits(straight) -> None:
    sc, truth = straight
    sec = truth.section
    lane, arc, v = np.zeros(3, dtype=np.int64), np.array([100.0, 400.0, 900.0]), np.full(3, 25.0)
    f = np.array([0.8, 1.0, 1.2])
    plain, _, _ = section_observations(sec, lane, arc, v, np.ones(3, bool), "lookahead")
    own, _, _ = section_observations(
        sec, lane, arc, v, np.ones(3, bool), "lookahead", None, None, f
    )
    assert np.allclose(own[:, [1, 4]], plain[:, [1, 4]] * f[:, None])
    assert np.array_equal(own[:, [0, 2, 3, 5]], plain[:, [0, 2, 3, 5]])
    # The deployment's observation scales the same columns.
    lane_id = next(iter(sec.lanes))
    st = VehicleStates(
        ("a", "b"), [lane_id, lane_id], np.array([100.0, 400.0]), np.full(2, 25.0), np.zeros(2)
    )
    args = (LaneTable(sec), "lookahead", ["a", "b"], np.arange(2), [lane_id] * 2, st)
    rest = ([("b", 293.0), ("", -1.0)], Table((5.0, 2.5, 4.5)), np.full(2, np.inf))
    base = observe_rows(*args, *rest)[0]
    sc = SimpleNamespace(seed=1, policy=SimpleNamespace(driver_speed="memory", observation="paper"))
    q = ratio_quantiles(np.array([0.75, 25.0 / 27.5, 1.25]))  # median: 25 m/s on 27.5
    mine = observe_rows(*args, *rest, DriverSpeeds(q, sc, 0))[0]
    factor = base[:, [0]] / base[:, [1]] / (25.0 / 27.5)  # both at 25 m/s when first seen
    assert np.allclose(mine[:, [1, 4]], base[:, [1, 4]] * factor)
    assert np.array_equal(mine[:, [0, 2, 3, 5]], base[:, [0, 2, 3, 5]])


def test_a_faster_driver_cruises_faster_under_the_gipps_prior() -> None:
    prior = {
        "speed_factor": 1.0,
        "accel_mps2": 2.0,
        "decel_mps2": 4.5,
        "tau_s": 1.0,
        "min_gap_m": 2.5,
        "veh_length_m": 5.0,
        "dt_s": 0.5,
    }
    agent = Agent(observation="paper", prior="gipps", prior_params=prior, residual_bound_mps2=0.0)
    # Free road, 300 s from 20 m/s: each driver settles at its factor x the limit.
    for f in (0.9, 1.1):
        v = 20.0
        for _ in range(600):
            obs = torch.tensor([[v, LIMIT_MPS * f, 250.0, 0.0]])
            v = max(0.0, v + 0.5 * float(agent.mean_action(obs)))
        assert abs(v - f * LIMIT_MPS) < 0.3


def test_with_driver_factors_sets_hidden_slots_only() -> None:
    valid = np.array([[True, True, True, False]] * 50)
    hidden = np.array([[False, True, True, False]] * 50)
    q = ratio_quantiles(np.linspace(0.8, 1.2, 21))
    obs0 = np.tile(
        [[30.0, 30.0, 250.0, 0.0], [27.0, 30.0, 250.0, 0.0], [33.0, 30.0, 250.0, 0.0]], (50, 1)
    )
    for kind in ("drawn", "memory"):
        f = with_driver_factors(Slots(valid, hidden), kind, q, 11, obs0).driver_factor
        assert np.all(f[~(valid & hidden)] == 1.0)
        again = with_driver_factors(Slots(valid, hidden), kind, q, 11, obs0).driver_factor
        assert np.array_equal(f, again)
    drawn = with_driver_factors(Slots(valid, hidden), "drawn", q, 11, obs0).driver_factor
    assert drawn[valid & hidden].std() > 0.05
    memory = with_driver_factors(Slots(valid, hidden), "memory", q, 11, obs0).driver_factor
    assert np.allclose(memory[:, 1:3], [0.9, 1.1])


def test_a_checkpoint_keeps_its_drivers_and_names_a_mismatch(straight, tmp_path: Path) -> None:
    sc, _ = straight
    drawn = load_scenario(straight_scenario(tmp_path / "drawn", "drawn"))
    q = ratio_quantiles(np.linspace(0.8, 1.2, 21))
    agent = Agent(observation=drawn.policy.observation, prior="gipps", driver_speed=q)
    assert np.allclose(agent.state_dict()["driver_speed"].numpy(), q)
    path = tmp_path / "policy.pt"
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "signature": signature(drawn),
            "state_dict": agent.state_dict(),
            "hidden_size": agent.hidden_size,
            "prior": "gipps",
            "driver_speed": "drawn",
        },
        path,
    )
    assert load_checkpoint(path, drawn)["driver_speed"] == "drawn"
    with pytest.raises(UserError, match="policy.driver_speed = 'drawn'.*has 'none'"):
        load_checkpoint(path, sc)

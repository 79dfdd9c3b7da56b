"""Lower bounds reached with nothing holding them (``policy.driver_ratios = "reached"``): a
vehicle that never cruised freely long enough but whose top speed nothing held it at (not
accelerating, no vehicle within a free gap, or a faster leader pulling away) gives its own
ratio there (``env.observed_drivers.unheld``, ``ObservedDrivers.reached``). Kaplan-Meier takes such
a top for a lower bound and gives its weight to the few fast exact ratios above it: on the
signalised arterial 521 its median was 1.12 where the observed drivers' true speedFactors'
median is 1.00."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from section_files import routes_file, section_scenario, vtype

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import netconvert  # noqa: E402

from macromicro_sumo.env.driver_speed_ratios import ObservedDrivers, ratio_estimate  # noqa: E402
from macromicro_sumo.env.observed_drivers import (
    CRUISE_ACCEL_MPS2,
    driver_ratios,
    observed_drivers,
    unheld,
)
from macromicro_sumo.road.section import NO_LEADER_GAP_M, STOP  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402

LIMIT_MPS = 15.0


def test_reached_bounds_give_the_median_where_kaplan_meier_does_not():
    """600 drivers of normal desired ratios N(1, 0.1); the fast cruise freely less often
    (one in five on average, as on 521); of the others 60% reach their own ratio (a top
    0.98-1.0 of it, flagged reached), the rest are held far below it (0.3-0.9). The exact
    ratios' median is 0.04 low; Kaplan-Meier's is 0.17 high; with the reached tops as
    ratios it is within 0.02 of the truth."""
    rng = np.random.default_rng(0)
    n = 600
    r = rng.normal(1.0, 0.1, n)
    free = rng.random(n) < np.clip(0.2 - 1.0 * (r - 1.0), 0.05, 0.5)
    near = rng.random(n) < 0.6
    bound = np.where(near, r * rng.uniform(0.98, 1.0, n), r * rng.uniform(0.3, 0.9, n))
    keys = [(0, f"v{i}") for i in range(n)]
    drivers = ObservedDrivers(
        {k: x for k, x, f in zip(keys, r, free, strict=True) if f},
        np.empty((0, 4)),
        np.empty(0),
        [],
        {k: b for k, b, f in zip(keys, bound, free, strict=True) if not f},
        frozenset(k for k, f, m in zip(keys, free, near, strict=True) if m and not f),
    )
    truth = float(np.median(r))
    km, reached = ratio_estimate(drivers), ratio_estimate(drivers, "reached")
    assert km.median - truth > 0.1  # Kaplan-Meier: the bounds' weight on the fast exact ones
    assert reached.median == pytest.approx(truth, abs=0.02)
    assert reached.reached == len(drivers.reached) > 200
    assert reached.exact == int(free.sum()) + reached.reached
    assert reached.record()["reached"] == reached.reached and "reached" not in km.record()
    # Without a reached bound it is Kaplan-Meier's, value for value.
    plain = ObservedDrivers(drivers.ratio, drivers.obs, drivers.accel, [], drivers.lower)
    assert np.array_equal(ratio_estimate(plain, "reached").quantiles, km.quantiles)


def test_unheld_samples_by_hand():
    """At 12 m/s: no leader, or a standing obstacle beyond the free gap (2 s x v + 5 m =
    29 m), is unheld; a faster leader 17 m ahead (1 s x v + 5 m) is, 16 m ahead is not;
    a leader as fast, or slower even 40 m ahead, holds the car; accelerating, the next
    speed unknown, or standing, it is not at its own speed."""
    v = np.array([12.0, 12.0, 12.0, 13.0, 12.0, 12.0, 12.0, 11.0, 12.0, 12.0])
    leader = np.array([-1, STOP, 3, -1, 3, -1, 5, -1, -1, -1])
    gap = np.array([NO_LEADER_GAP_M, 30.0, 17.0, NO_LEADER_GAP_M, 16.0, 99, 40.0, 99, 99, 99])
    accel = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, CRUISE_ACCEL_MPS2, np.nan, 0.0])
    limit = np.full(10, 15.0)
    got = unheld(v, limit, accel, gap, leader)
    assert got[:4].tolist() == [True, True, True, True]
    assert not got[4]  # a faster leader too near
    assert not got[6]  # a leader as fast (row 5's 12 m/s), 40 m ahead
    assert not got[7] and not got[8]  # accelerating; last sample
    slow = unheld(np.array([1.0]), np.array([15.0]), np.zeros(1), np.full(1, 99.0), np.full(1, -1))
    assert not slow[0]  # standing: below CRUISE_MIN_SHARE of the limit
    assert not unheld(v[:1], limit[:1], accel[:1], np.array([28.0]), np.array([STOP]))[0]


def follow_scenario(folder: Path, policy: dict | None = None) -> Path:
    """A one-lane 300 m road at 15 m/s, SUMO's Krauss without dawdling: car "a" (speedFactor
    0.85) with "b" (0.8) inserted 1 s behind it; later "c" (0.6) with "d" (0.8) 1 s
    behind. b cruises at 12 m/s as a pulls away, never 29 m behind it (its free gap) on the
    road; d is held at c's 9 m/s."""
    net = netconvert(
        folder,
        '<node id="a" x="0" y="0"/>\n<node id="b" x="300" y="0"/>',
        f'<edge id="E" from="a" to="b" numLanes="1" speed="{LIMIT_MPS}"/>',
    )
    routes = routes_file(
        folder / "r.rou.xml",
        [vtype(t, length=5, minGap=2.5, speedFactor=f, speedDev=0, sigma=0)
         for t, f in (("fast", 0.85), ("own", 0.8), ("slow", 0.6))],
        ['<vehicle id="a" type="fast" route="r" depart="0" departSpeed="max"/>',
         '<vehicle id="b" type="own" route="r" depart="1" departSpeed="max"/>',
         '<vehicle id="c" type="slow" route="r" depart="60" departSpeed="max"/>',
         '<vehicle id="d" type="own" route="r" depart="61" departSpeed="max"/>'],
        ['<route id="r" edges="E"/>'],
    )  # fmt: skip
    return section_scenario(
        folder / "follow.toml",
        net,
        routes,
        ["E"],
        seed=5,
        penetration=1.0,
        simulation={"warmup_s": 0.0, "duration_s": 120.0, "n_runs": 1},
        detectors={"interval_s": 30.0, "auto_spacing_m": 200.0},
        policy=policy or {},
    )


def test_a_car_at_its_own_speed_behind_a_faster_leader_is_reached(tmp_path: Path):
    """Real SUMO: b never cruises freely (a bound), but a pulls away ahead of it at its own
    12 m/s: reached, its bound its ratio 0.8. d, held behind its slower leader, is a bound
    not reached. With policy.driver_ratios = "reached" the scenario's estimate counts
    b's (fewer than 30 exact ratios: SUMO's default quantiles either way)."""
    sc = load_scenario(follow_scenario(tmp_path))
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    drivers = observed_drivers(sc, truth, truth.runs)
    assert (0, "a") in drivers.ratio and drivers.ratio[(0, "a")] == pytest.approx(0.85, abs=0.01)
    assert (0, "b") in drivers.lower and (0, "b") not in drivers.ratio
    assert drivers.lower[(0, "b")] == pytest.approx(0.8, abs=0.01)
    assert (0, "b") in drivers.reached
    # d's top: inserted at 10.3 m/s, braking to c's 9 m/s; its own 12 m/s never shows
    assert (0, "d") in drivers.lower and drivers.lower[(0, "d")] < 0.75
    assert (0, "d") not in drivers.reached
    assert sc.policy.driver_ratios == "kaplan_meier"
    assert driver_ratios(sc, truth, truth.runs).reached == 0
    (tmp_path / "r").mkdir()
    opted = load_scenario(follow_scenario(tmp_path / "r", {"driver_ratios": "reached"}))
    assert driver_ratios(opted, truth, truth.runs).reached == 1

"""The desired-speed ratios' free test (``env.observed_drivers.observed_drivers``): it reads the
bumper gap to the leader (the spacing less the leader's length), not the front-to-front
spacing, and a standing sample is not cruising. Before, a car crawling behind a 12 m truck
(or standing 14.5 m behind it in a queue) passed the spacing test, and its top speed was
taken as its exact desired-speed ratio (arterial 521: 0.28-0.54 of the limit)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from section_files import routes_file, section_scenario, vtype

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import netconvert  # noqa: E402

from macromicro_sumo.env.observed_drivers import (
    CRUISE_MIN_SHARE,
    FREE_GAP_M,
    FREE_HEADWAY_S,
    cruising,
    free_gap_m,
    observed_drivers,
)
from macromicro_sumo.road.section import NO_LEADER_GAP_M, STOP  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402

LIMIT_MPS = 15.0
TRUCK_MPS = 3.0  # the truck's maxSpeed: the cars behind it crawl at 0.2 of the limit


def truck_scenario(folder: Path, observation: str) -> Path:
    """A one-lane 1.5 km road at 15 m/s: a 12 m truck whose maxSpeed is 3 m/s, then cars
    (speedFactor 1, no deviation) inserted behind it every 4 s at the highest safe speed,
    every vehicle observed. The first car follows the truck ~6 m behind its rear at 3 m/s
    (front-to-front 17.5 m, above 2 s x 3 m/s + 10 m)."""
    net = netconvert(
        folder,
        '<node id="a" x="0" y="0"/>\n<node id="b" x="1500" y="0"/>',
        f'<edge id="E" from="a" to="b" numLanes="1" speed="{LIMIT_MPS}"/>',
    )
    routes = routes_file(
        folder / "r.rou.xml",
        [vtype("car", length=5, minGap=2.5, speedFactor=1, speedDev=0),
         vtype("truck", length=12, minGap=2.5, speedFactor=1, speedDev=0, maxSpeed=TRUCK_MPS)],
        ['<vehicle id="t" type="truck" route="r" depart="0" departSpeed="max"/>',
         '<flow id="c" type="car" route="r" begin="4" end="40" period="4" departSpeed="max"/>'],
        ['<route id="r" edges="E"/>'],
    )  # fmt: skip
    return section_scenario(
        folder / "truck.toml",
        net,
        routes,
        ["E"],
        seed=5,
        penetration=1.0,
        simulation={"warmup_s": 0.0, "duration_s": 120.0, "n_runs": 1},
        detectors={"interval_s": 30.0, "auto_spacing_m": 1000.0},
        policy={"observation": observation},
    )


@pytest.mark.parametrize("observation", ["lookahead", "lookahead_gap"])
def test_a_car_crawling_behind_a_truck_gives_a_lower_bound(tmp_path: Path, observation: str):
    """Real SUMO: the car right behind the truck drives at 3 m/s, 0.2 of the limit, for two
    minutes with its leader 17.5 m ahead front to front: a lower bound of its ratio, not
    the ratio (before: an exact 0.2, in either observation layout)."""
    sc = load_scenario(truck_scenario(tmp_path, observation))
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    traj = truth.trajectories
    first = traj[traj["vehicle_id"] == "c.0"]
    assert len(first) > 100 and first["speed_mps"].iloc[-50:].max() < TRUCK_MPS + 0.5
    drivers = observed_drivers(sc, truth, truth.runs)
    assert (0, "c.0") in drivers.lower and (0, "c.0") not in drivers.ratio
    assert drivers.lower[(0, "c.0")] < 0.5
    assert not [r for r in drivers.ratio.values() if r < 0.5]  # no car has a crawl's ratio


def test_the_free_test_reads_the_bumper_gap_and_skips_standing_samples():
    """By hand: at 3 m/s with the leader 17.5 m ahead front to front the car is free behind
    a 5 m car (gap 12.5 m >= 2 s x 3 m/s + 5 m), not behind a 12 m truck (5.5 m); the
    spacing test (>= 16 m) took both as free. A standing obstacle 20 m ahead (the distance
    alone, or a standing car of the own length beyond it) is the same gap either way; no
    leader is free; a car below ``CRUISE_MIN_SHARE`` of the limit does not cruise."""
    spacing = np.array([17.5, 17.5, 20.0, NO_LEADER_GAP_M, 17.5])
    v = np.full(5, 3.0)
    assert (spacing[:2] >= v[:2] * FREE_HEADWAY_S + FREE_GAP_M).all()  # the old test
    leader = np.array([2, 4, STOP, -1, 0])
    length = np.array([5.0, 5.0, 12.0, 5.0, 5.0])
    gap = free_gap_m(spacing, leader, length, with_length=False)
    assert gap[:4].tolist() == [5.5, 12.5, 22.5, NO_LEADER_GAP_M]
    standing = 20.0 + 2.5 + length[2]  # road.leaders.standing_spacing_m of a lane end
    with_len = free_gap_m(np.array([standing]), np.array([STOP]), length[2:3], with_length=True)
    assert with_len[0] == pytest.approx(gap[2])
    limit = np.full(5, 15.0)
    free = cruising(v, limit, np.zeros(5), gap)
    assert free[:4].tolist() == [False, True, True, True]
    slow = np.array([0.9 * CRUISE_MIN_SHARE * 15.0])
    assert not cruising(slow, limit[:1], np.zeros(1), np.array([NO_LEADER_GAP_M]))[0]
    # A leader of unknown length counts as a car: the spacing test as before.
    unknown = free_gap_m(spacing[:1], np.array([1]), np.array([np.nan, np.nan]), False)
    assert unknown[0] == pytest.approx(spacing[0] - (FREE_GAP_M - 5.0))

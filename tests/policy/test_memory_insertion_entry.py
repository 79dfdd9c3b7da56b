"""``policy.driver_entry = "insertion"`` (opt-in): a first sight not held by the free-gap rule
(``held_at_sight``) but at the speed SUMO inserts a vehicle at with departSpeed "max" behind a
slower leader (``at_insertion``: Krauss's safe speed) says only that the driver's desired
speed is at least its speed: it takes "drawn"'s factor at its level, as a held one does.
Drawn 522 (stop 48, hM48): such entries kept ratios of 0.7-0.9 and led slow platoons on the
one-lane edges.
Real SUMO: one car inserted at departSpeed "max" 45 m behind a slow truck (at vsafe, below
its desired speed), one slow driver inserted the same way (at its own desired speed)."""

from __future__ import annotations

from pathlib import Path

import libsumo
import numpy as np
from conftest import netconvert

from macromicro_sumo.env.driver_speed import (
    QUANTILE_LEVELS,
    at_insertion,
    factors_at,
    held_at_sight,
    ratio_quantiles,
    sight_factors,
)
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

LIMIT_MPS = 25.0
Q = ratio_quantiles(np.linspace(0.8, 1.2, 41))  # median 1.0, range 0.8-1.2


def _inserted_sights(folder: Path) -> np.ndarray:
    """First sights [v, limit, bumper gap, delta v, limit] of two vehicles inserted at
    departSpeed "max" on one lane at 25 m/s, each when a truck ahead at 10 m/s is 45 m
    further (beyond the free gap 2 s x v + 5 m at 18-21 m/s): a Krauss car with speed factor
    1 (its desired speed 25 m/s; SUMO puts it in at the safe speed) and one with speed factor
    0.7 (17.5 m/s, below the safe speed: put in at its own)."""
    net = netconvert(
        folder,
        '<node id="a" x="0" y="0"/>\n<node id="b" x="2000" y="0"/>',
        f'<edge id="E" from="a" to="b" numLanes="1" speed="{LIMIT_MPS}"/>',
    )
    routes = folder / "r.rou.xml"
    routes.write_text(
        "<routes>\n"
        '    <vType id="truck" vClass="truck" length="12" maxSpeed="10" speedDev="0"/>\n'
        '    <vType id="car" length="5" minGap="2.5" speedDev="0" sigma="0"/>\n'
        '    <vType id="slow" length="5" minGap="2.5" speedDev="0" sigma="0" speedFactor="0.7"/>\n'
        '    <route id="r" edges="E"/>\n'
        '    <vehicle id="t0" type="truck" route="r" depart="0" departSpeed="10"/>\n'
        '    <vehicle id="c" type="car" route="r" depart="5.7" departSpeed="max"/>\n'
        '    <vehicle id="t1" type="truck" route="r" depart="60" departSpeed="10"/>\n'
        '    <vehicle id="s" type="slow" route="r" depart="65.7" departSpeed="max"/>\n'
        "</routes>\n"
    )
    sim = Simulation(SumoOptions(net, (), 0.5, 3, route_files=(routes,), user_demand=True))
    rows = {}
    try:
        for _ in range(200):
            sim.step()
            for vid, lead in (("c", "t0"), ("s", "t1")):
                if vid in rows or vid not in sim.vehicle_ids():
                    continue
                v, vl = libsumo.vehicle.getSpeed(vid), libsumo.vehicle.getSpeed(lead)
                gap = (
                    libsumo.vehicle.getLanePosition(lead)
                    - libsumo.vehicle.getLength(lead)
                    - libsumo.vehicle.getLanePosition(vid)
                )
                rows[vid] = [v, LIMIT_MPS, gap, v - vl, LIMIT_MPS]
    finally:
        sim.close()
    return np.array([rows["c"], rows["s"]])


def test_a_max_insertion_behind_a_slow_truck_is_at_insertion_and_drawn_above(
    tmp_path: Path,
) -> None:
    obs = _inserted_sights(tmp_path)
    v, gap = obs[:, 0], obs[:, 2]
    assert 16.0 < v[0] < 24.0  # below its 25 m/s: SUMO's safe speed behind the truck
    assert abs(v[1] - 17.5) < 0.01  # at its own desired speed, below the safe speed
    assert np.all(gap >= v * 2.0 + 5.0)  # beyond the free gap: neither is held
    assert not held_at_sight(obs, True).any()
    np.testing.assert_array_equal(at_insertion(obs, True), [True, False])
    # spacing layout (leader column front to front): the same reading
    spacing = obs.copy()
    spacing[:, 2] += 5.0
    np.testing.assert_array_equal(at_insertion(spacing, False), [True, False])

    levels = np.array([0.5, 0.3])
    held = sight_factors(Q, obs, levels, "held", True)
    ins = sight_factors(Q, obs, levels, "insertion", True)
    own = v / LIMIT_MPS  # the ratios over the median 1.0
    np.testing.assert_allclose(held, np.clip(own, 0.8, 1.2))  # both kept under "held"
    assert ins[1] == held[1]  # the slow one keeps its own ratio
    assert ins[0] == factors_at(Q, levels[:1])[0] and ins[0] > held[0]  # drawn: the median


def test_at_insertion_needs_a_slower_leader_near() -> None:
    """No leader, a faster leader, a sight far below or above the safe speed: not at it."""
    vl, gap = 10.0, 45.0
    vsafe = -4.5 + np.sqrt(4.5**2 + vl**2 + 2 * 4.5 * (gap - 2.5))
    v = np.array([vsafe, vsafe, vsafe - 3.0, vsafe + 1.0, vsafe - 1.0, vsafe])
    lead = np.array([gap, NO_LEADER_GAP_M, gap, gap, gap, gap])
    dv = v - vl
    dv[5] = -1.0  # a faster leader
    limit = 20.0  # every sight moving (above 0.65 of the median), none clipped
    obs = np.column_stack([v, np.full(6, limit), lead, dv, np.full(6, limit)])
    np.testing.assert_array_equal(at_insertion(obs, True), [True, False, False, False, True, False])
    # the other entries leave these sights' factors as they were
    levels = np.linspace(0.1, 0.9, 6)
    for entry in ("queued", "held"):
        f = sight_factors(Q, obs, levels, entry, True)
        np.testing.assert_allclose(f, np.clip(v / limit, 0.8, 1.2))
    assert QUANTILE_LEVELS[0] == 0.0

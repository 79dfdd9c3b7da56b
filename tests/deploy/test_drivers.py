"""Drivers on live SUMO: what a driven vehicle sees (leaders across an added lane, red
lights) and that it acts on it. Real SUMO, a small policy cloned from IDM."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import small_section_scenario
from deploy_nets import idm_agent, light_net, merge_net

from macromicro_sumo.deploy.drivers import SectionSpeedDriver, section_observations
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.deploy.slots import LaneCache
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run


class Recording(SectionSpeedDriver):
    """A policy driver that also keeps every step's observations and lane states."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.seen: list[tuple[list[str], np.ndarray, dict]] = []

    def drive(self, sim, vids, st) -> None:
        if self.has_lights is None:
            self.has_lights = sim.has_traffic_lights()
        states = {
            v: (lane, p, s, a)
            for v, lane, p, s, a in zip(
                st.ids, st.lanes, st.pos_m, st.speed_mps, st.accel_mps2, strict=True
            )
        }
        # The dictionary form (the demand env's) sees what the driver's own arrays give.
        obs, _, _ = section_observations(self, sim, vids, states)
        rows = np.array([st.index[v] for v in vids])
        own = self.observe(sim, vids, rows, st)[0]
        np.testing.assert_array_equal(obs, own)
        self.seen.append((vids, obs, states))
        super().drive(sim, vids, st)


def _run(sc, driver, additional: tuple[Path, ...] = ()) -> object:
    sim = Simulation(
        SumoOptions(
            sc.resolve(sc.network.net_file),
            additional,
            sc.simulation.step_length_s,
            sc.seed,
            route_files=tuple(sc.resolve(r) for r in sc.network.route_files),
            user_demand=True,
        )
    )
    try:
        df, stats = record_run(sim, sc, driver.section, 0, driver)
    finally:
        sim.close()
    return df, stats


@pytest.fixture(scope="module")
def merge_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return merge_net(tmp_path_factory.mktemp("merge"))


def _through_lane(section, lane_id: str) -> tuple[int, int] | None:
    """(edge, lane) of the through lane holding ``lane_id``: A's lanes 0 and 1 go on as B's
    1 and 2 and C's 0 and 1 (``merge_net``); a junction lane counts as the lane it enters."""
    e, idx, _, _ = section.lanes[lane_id]
    if lane_id.startswith(":"):
        e += 1
    through = {0: {0: 0, 1: 1}, 1: {1: 0, 2: 1}, 2: {0: 0, 1: 1}}[e]
    return (0, through[idx]) if idx in through else None


def test_leader_across_an_added_lane_is_the_physically_next_vehicle(
    merge_files: tuple[Path, Path], tmp_path: Path
) -> None:
    """Where B adds a lane on the right, A's lane 0 goes on as B's lane 1: the spacing a
    driver on A sees is to the next vehicle on its through lane (lane indices differ)."""
    net, routes = merge_files
    sc = small_section_scenario(
        tmp_path, net, routes, ["A", "B", "C"], instrumented={"penetration": 0.01}
    )
    section = read_section(net, ["A", "B", "C"], False)
    agent = idm_agent("lookahead", 30.0)
    drv = Recording(sc, section, 0, policy_batch(agent), "sumo")
    _run(sc, drv)
    crossing = checked = 0
    for vids, obs, states in drv.seen:
        pos = {}
        for v, (lane, p, _, _) in states.items():
            if lane in section.lanes and _through_lane(section, lane) is not None:
                hit = section.lanes[lane]
                pos[v] = (_through_lane(section, lane), hit[2] + p * hit[3], lane)
        for i, v in enumerate(vids):
            if v not in pos:
                continue
            lane_key, arc, lane = pos[v]
            ahead = [(a - arc, w) for w, (k, a, _) in pos.items() if k == lane_key and a > arc]
            if not ahead:
                continue
            gap, w = min(ahead)
            if gap >= NO_LEADER_GAP_M - 10 or obs[i, 2] >= NO_LEADER_GAP_M:
                continue
            checked += 1
            # SUMO's distance along the lanes vs arc positions (junction shapes): 1 m.
            assert abs(obs[i, 2] - gap) < 1.5, (v, lane, w, pos[w][2], obs[i, 2], gap)
            if not lane.startswith(":") and section.lanes[lane][0] == 0 and pos[w][2][0] == "B":
                crossing += 1
                # The same lane index on B is another lane: an index lookup would be wrong.
                assert section.lanes[lane][1] != section.lanes[pos[w][2]][1]
    assert checked > 500 and crossing > 20, (checked, crossing)


def test_a_red_light_stops_a_policy_driven_vehicle_before_the_stop_line(tmp_path: Path) -> None:
    net, routes, red = light_net(tmp_path)
    sc = small_section_scenario(
        tmp_path,
        net,
        routes,
        ["A", "B"],
        instrumented={"ids": ["probe"]},
        simulation={"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 2},
    )
    section = read_section(net, ["A", "B"], False)
    agent = idm_agent("lookahead", 20.0)
    # Safety "none": SUMO neither brakes for the light nor caps the command: only the
    # policy, seeing the red light as a standing leader, can stop the car.
    drv = SectionSpeedDriver(sc, section, 0, policy_batch(agent), "none")
    df, stats = _run(sc, drv, (red,))
    v0 = df[df["vehicle_id"] == "v0"]
    line = float(section.lengths_m[0])
    assert v0["arc_m"].max() < line, v0["arc_m"].max()
    last = v0.iloc[-1]
    assert last["speed_mps"] < 0.1 and line - last["arc_m"] < 15.0, last.to_dict()
    assert stats["collisions"] == 0 and drv.stats.vehicle_steps_driven > 100


def test_one_read_per_step_gives_what_subscriptions_give(
    merge_files: tuple[Path, Path], tmp_path: Path
) -> None:
    """``Simulation.vehicle_states`` (getters, read once per step and shared) and
    ``leaders`` hold, step by step, what the subscriptions the deployment used held: the
    same vehicles in the same order, the same numbers; a teleporting vehicle (lane "") is
    not on the road. With a policy driving, so that speed commands are in play."""
    net, routes = merge_files
    sc = small_section_scenario(
        tmp_path, net, routes, ["A", "B", "C"], instrumented={"penetration": 0.2}
    )
    section = read_section(net, ["A", "B", "C"], False)
    drv = SectionSpeedDriver(sc, section, 0, policy_batch(idm_agent("lookahead", 30.0)), "sumo")
    sim = Simulation(
        SumoOptions(
            net, (), sc.simulation.step_length_s, sc.seed, route_files=(routes,), user_demand=True
        )
    )
    compared = 0
    try:
        for _ in range(240):
            drv.before_step(sim)
            sim.step()
            sim.subscribe_driving(sim.departed(), NO_LEADER_GAP_M)
            subs = {v: s for v, s in sim.read_lane_states().items() if s[0]}
            st = sim.vehicle_states()
            assert sim.vehicle_states() is st  # one read per step
            assert list(st.ids) == list(subs) == sorted(st.ids)
            for i, v in enumerate(st.ids):
                assert (st.lanes[i], st.pos_m[i], st.speed_mps[i], st.accel_mps2[i]) == subs[v]
            lead = sim.read_leaders()
            assert sim.leaders(list(st.ids), NO_LEADER_GAP_M) == [lead[v] for v in st.ids]
            compared += len(st.ids)
    finally:
        sim.close()
    assert compared > 2000 and drv.stats.vehicle_steps_driven > 1000


def test_a_lane_cache_asks_again_on_another_lane_at_its_step_and_after_forget() -> None:
    """``deploy.slots.LaneCache``: due where never asked, where the vehicle is on another
    lane than the one asked on, and from the step it was stored to be asked again; not
    due otherwise; a forgotten slot is due again, and the cache grows by doubling."""
    cache = LaneCache(2, np.nan)
    slots, lanes = np.array([0, 1]), np.array([3, 4])
    assert cache.due(slots, lanes, 0).tolist() == [0, 1]  # never asked
    cache.store(slots, lanes, np.array([120.0, np.inf]), np.array([np.inf, 20.0]))
    assert cache.due(slots, lanes, 19).size == 0
    assert cache.due(slots, lanes, 20).tolist() == [1]  # its step has come
    assert cache.due(slots, np.array([5, 4]), 19).tolist() == [0]  # changed lane
    assert cache.value[slots].tolist() == [120.0, np.inf]
    cache.forget(slots[:1])
    assert cache.due(slots, lanes, 19).tolist() == [0]
    cache.grow()
    assert len(cache.lane) == 4 and cache.due(np.array([3]), np.array([3]), 0).tolist() == [0]
    assert np.isnan(cache.value[3])


def test_a_lane_cache_put_is_a_store_of_one_slot() -> None:
    """``LaneCache.put`` (the drivers' scalar writes for the few vehicles due a step) leaves
    the arrays ``store`` leaves, slot by slot."""
    one, many = LaneCache(4, np.nan), LaneCache(4, np.nan)
    slots, lanes = np.array([2, 0]), np.array([7, 3])
    values, again = np.array([np.inf, 81.5]), np.array([20.0, np.inf])
    many.store(slots, lanes, values, again)
    for i in range(len(slots)):
        one.put(int(slots[i]), int(lanes[i]), float(values[i]), float(again[i]))
    for name in ("lane", "value", "again"):
        np.testing.assert_array_equal(getattr(one, name), getattr(many, name))
    assert one.due(slots, lanes, 19).size == 0 and one.due(slots, lanes, 20).tolist() == [0]


def test_emergency_brakings_are_counted_per_vehicle_threshold(tmp_path: Path) -> None:
    """``count_brakings`` counts a vehicle where its acceleration is below minus its own
    vType's decel by more than the tolerance, also where the whole step is skipped because
    nobody is below the loosest threshold (the least decel met): over seeded accelerations
    around each vehicle's threshold on a real SUMO run's vehicles (two vTypes of decel 4.5
    and 7.5, light_net), the per-vehicle count."""
    from macromicro_sumo.deploy.drivers import BRAKING_TOLERANCE_MPS2, SectionDriver
    from macromicro_sumo.sumo.states import VehicleStates

    net, routes, _red = light_net(tmp_path)
    text = routes.read_text().replace('id="probe" type="car"', 'id="probe" type="hard"')
    routes.write_text(text.replace("<routes>", '<routes>\n<vType id="hard" decel="7.5"/>'))
    sc = small_section_scenario(tmp_path, net, routes, ["A", "B"])
    drv = SectionDriver(sc, read_section(net, ["A", "B"], False), 0)
    sim = Simulation(SumoOptions(net, (), 0.5, 1, route_files=(routes,), user_demand=True))
    try:
        for _ in range(40):
            drv.before_step(sim)
            sim.step()
        st = sim.vehicle_states()
    finally:
        sim.close()
    decel = np.array([drv.decel_of[v] for v in st.ids])
    assert len(st.ids) >= 2 and {4.5, 7.5} <= set(decel.tolist()), decel
    rng = np.random.default_rng(3)
    expected = counted = 0
    for _ in range(300):
        limit = -decel - BRAKING_TOLERANCE_MPS2
        accel = limit + rng.choice([-1e-9, 0.0, 1e-9, -0.5, 0.5, 3.5], len(decel))
        accel = np.where(rng.random(len(decel)) < 0.2, np.nextafter(limit, -np.inf), accel)
        before = drv.stats.emergency_brakings
        drv.count_brakings(VehicleStates(st.ids, st.lanes, st.pos_m, st.speed_mps, accel))
        got = drv.stats.emergency_brakings - before
        assert got == int(np.count_nonzero(accel < limit)), (accel, limit)
        expected += got
        counted += got == 0
    assert expected > 100 and counted > 10, (expected, counted)

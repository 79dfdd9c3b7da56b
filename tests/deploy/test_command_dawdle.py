"""``deploy.command_dawdle``: each driven vehicle's acceleration at most SUMO's Krauss mean
dawdled acceleration a - sigma / 2 min(v, a) (``deploy.safety.dawdled_accel``): the closed
form, the commands of ``speed_commands`` with and without it (numpy), and cars driven in
real SUMO from a standstill by a policy that always asks the most."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from deploy_nets import queue_at_light, sparse_merge
from test_safety import _run_section

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.safety import dawdled_accel, speed_commands
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.load import load_scenario


def test_the_mean_dawdled_acceleration() -> None:
    """Below v = a a car loses sigma v / 2 of its a, from v = a on sigma a / 2: 2.6 m/s^2 at
    a standstill, 1.95 from 2.6 m/s on at SUMO's defaults (a = 2.6, sigma = 0.5); a
    truck's 1.3 likewise; sigma 0 leaves a."""
    v = np.array([0.0, 1.0, 2.6, 10.0])
    np.testing.assert_allclose(dawdled_accel(2.6, v, 0.5), [2.6, 2.35, 1.95, 1.95])
    got = dawdled_accel(np.array([2.6, 1.3, 2.6, 1.3]), v, 0.5)
    np.testing.assert_allclose(got, [2.6, 1.3 - 0.25, 1.95, 0.975])
    np.testing.assert_allclose(dawdled_accel(2.6, v, 0.0), 2.6)


def _free(n: int, v: np.ndarray) -> tuple[np.ndarray, object]:
    obs = np.column_stack([v, np.full(n, 30.0), np.full(n, NO_LEADER_GAP_M), np.zeros(n)])
    obs = np.column_stack([obs, np.full(n, 30.0), np.full(n, 500.0)])  # the look-ahead

    def layer() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return np.full(n, NO_LEADER_GAP_M), np.full(n, 4.5), np.full(n, 9.0), np.full(n, -1)

    return obs, layer


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_commands_on_a_free_road(tmp_path: Path, sigma: float) -> None:
    """A policy asking 10 m/s^2 of cars at 0, 1, 5 and 20 m/s on a free road: without the
    dawdle (0) each gets v + a dt at the bound's 2.6; with sigma 0.5,
    v + (2.6 - 0.25 min(v, 2.6)) dt. A braking policy's cars are raised to the floor (a
    fifth of the limit), which reaches no further than that acceleration either."""
    sc = load_scenario(sparse_merge(tmp_path, deploy={"command_dawdle": sigma}))
    assert sc.deploy.command_dawdle == sigma
    v = np.array([0.0, 1.0, 5.0, 20.0])
    obs, layer = _free(4, v)
    dt, a_max = sc.simulation.step_length_s, sc.bounds.accel_mps2[1]
    cmd = speed_commands(sc, lambda o: np.full(len(o), 10.0), "sumo", DriveStats(), obs, layer)
    a = a_max - 0.5 * sigma * np.minimum(v, a_max)
    np.testing.assert_allclose(cmd, v + a * dt, rtol=0, atol=1e-12)
    brake = speed_commands(sc, lambda o: np.full(len(o), -1.0), "sumo", DriveStats(), obs, layer)
    floor = np.minimum(v + a * dt, sc.deploy.safety_floor_share * 30.0)
    np.testing.assert_allclose(brake, np.maximum(v - 1.0 * dt, floor), rtol=0, atol=1e-12)


GREEN_S = 60.0  # the queue's light turns green [s]


def _queue(tmp_path: Path, sigma: float) -> Path:
    """``deploy_nets.queue_at_light`` with B 300 m long, 60 s of green and
    ``deploy.command_dawdle``."""
    toml = tmp_path / f"queue_{sigma}.toml"
    return queue_at_light(toml, GREEN_S, {"command_dawdle": sigma}, b_m=300.0, after_s=60.0)


def test_a_queue_discharges_at_the_dawdled_acceleration_in_sumo(tmp_path: Path) -> None:
    """A queue at a real SUMO light, every car driven by a policy that always asks the
    bound (2.6 m/s^2): with sigma 0.5 no driven car accelerates faster than a - sigma / 2
    min(v, a), the queue's head reaches 1.95 m/s^2 beyond 2.6 m/s, and the queue crosses
    the line no earlier than without the setting (the 12th car 1 s later), as SUMO's
    dawdling Krauss drivers discharge slower than the policy's mean action; no collision,
    no teleport. Without it the head reaches 2.6."""
    most, crossed = {}, {}
    for sigma in (0.0, 0.5):
        sc = load_scenario(_queue(tmp_path / str(sigma), sigma))
        section = read_section(sc.resolve(sc.network.net_file), ["A", "B"], False)
        a_max, dt = sc.bounds.accel_mps2[1], sc.simulation.step_length_s
        drv = SectionSpeedDriver(sc, section, 0, lambda o, a=a_max: np.full(len(o), a), "sumo")
        light = sc.resolve(sc.network.net_file).parent / "light.add.xml"
        df, stats = _run_section(sc, drv, (light,))
        assert stats["collisions"] == 0 and stats["teleports"] == 0, (sigma, stats)
        d = df[~df["observed"]].sort_values(["vehicle_id", "time_s"])
        nxt = d.groupby("vehicle_id")[["speed_mps", "time_s"]].shift(-1)
        keep = (nxt["time_s"] - d["time_s"]) == dt
        v, a = d["speed_mps"][keep], ((nxt["speed_mps"] - d["speed_mps"]) / dt)[keep]
        cap = dawdled_accel(a_max, v.to_numpy(), sigma)
        assert (a.to_numpy() <= cap + 1e-6).all(), (sigma, float((a - cap).max()))
        most[sigma] = float(a[v > 3.0].max())
        past = d[d["arc_m"] > 150.0].groupby("vehicle_id")["time_s"].min().sort_values()
        assert len(past) == 12, past
        crossed[sigma] = past.to_numpy()
    assert most[0.5] == pytest.approx(1.95, abs=0.01) and most[0.0] == pytest.approx(2.6, abs=0.01)
    assert (crossed[0.5] >= crossed[0.0]).all() and crossed[0.5][-1] >= crossed[0.0][-1] + 1.0

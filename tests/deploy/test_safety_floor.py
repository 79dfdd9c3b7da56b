"""``deploy.safety_floor_on``: the vehicles the safety layer's floor raises. "all" (the
default) raises any command below a share of the limit, a moving car's braking in a queue
too; "standing" only a vehicle slower than ``STANDING_BELOW_MPS``, which still keeps a
policy that always brakes from holding cars standing: in numpy and in real SUMO."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from deploy_nets import sparse_merge
from test_safety import _run_section

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.safety import STANDING_BELOW_MPS, speed_commands
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.load import load_scenario


def _merge(folder: Path, floor_on: str) -> Path:
    """The merge of ``test_safety`` with ``deploy.safety_floor_on``."""
    return sparse_merge(folder, deploy={"safety_floor_on": floor_on})


@pytest.mark.parametrize("floor_on", ["all", "standing"])
def test_standing_raises_only_the_standing(tmp_path: Path, floor_on: str) -> None:
    """Three cars on a free 30 m/s lane, each commanded a full stop (a = -30 m/s^2): one at
    5 m/s, one at 0.5 m/s, one standing. "all" raises each to the floor (a fifth of the
    limit, at most its speed + 2.6 m/s^2 x 0.5 s); "standing" only those below 1 m/s, and
    the moving car's braking stands."""
    sc = load_scenario(_merge(tmp_path, floor_on))
    v = np.array([5.0, 0.5, 0.0])
    obs = np.column_stack([v, np.full(3, 30.0), np.full(3, NO_LEADER_GAP_M), np.zeros(3)])
    obs = np.column_stack([obs, np.full(3, 30.0), np.full(3, 500.0)])  # the look-ahead

    def layer() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return np.full(3, NO_LEADER_GAP_M), np.full(3, 4.5), np.full(3, 9.0), np.full(3, -1)

    stats = DriveStats()
    cmd = speed_commands(sc, lambda o: np.full(len(o), -30.0), "sumo", stats, obs, layer)
    a_max = sc.bounds.accel_mps2[1]
    reach = np.minimum(v + a_max * sc.simulation.step_length_s, 0.2 * 30.0)
    below = v < STANDING_BELOW_MPS
    raised = np.ones(3, bool) if floor_on == "all" else below
    np.testing.assert_allclose(cmd[raised], reach[raised])
    braked = np.maximum(v + sc.bounds.accel_mps2[0] * sc.simulation.step_length_s, 0.0)
    np.testing.assert_allclose(cmd[~raised], braked[~raised])
    assert stats.floor_acted == int(raised.sum())


def test_the_default_keeps_a_braking_stream_at_the_floor_where_standing_crawls(
    tmp_path: Path,
) -> None:
    """The trade-off "standing" makes (docs/deploy-log.md, Safety layer strictness): a policy
    that brakes at a_min whatever it sees moves at the floor (a fifth of the 30 m/s limit)
    under "all"; under "standing" it is raised only below 1 m/s and braked again, so it
    crawls at no more than one step's acceleration above that, and fewer cars pass."""
    speed, seen = {}, {}
    for floor_on in ("all", "standing"):
        sc = load_scenario(_merge(tmp_path / floor_on, floor_on))
        section = read_section(sc.resolve(sc.network.net_file), ["A", "B", "C"], False)
        a_min, a_max = sc.bounds.accel_mps2
        brake = lambda obs, a=a_min: np.full(len(obs), a)  # noqa: E731 (binds this loop's a_min)
        drv = SectionSpeedDriver(sc, section, 0, brake, "sumo")
        df, stats = _run_section(sc, drv)
        assert stats["collisions"] == 0 and stats["teleports"] == 0, (floor_on, stats)
        driven = df[~df["observed"]]
        speed[floor_on], seen[floor_on] = driven["speed_mps"], driven["vehicle_id"].nunique()
    floor = sc.deploy.safety_floor_share * 30.0
    assert abs(speed["all"].median() - floor) < 0.05, speed["all"].describe()
    crawl = STANDING_BELOW_MPS + a_max * sc.simulation.step_length_s
    assert speed["standing"].quantile(0.75) <= crawl + 0.01, speed["standing"].describe()
    assert seen["standing"] < seen["all"], seen

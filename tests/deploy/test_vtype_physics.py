"""A driven vehicle is held to its vType's maxSpeed and accel (its physics, not safety): SUMO
does not impose them on a speed command under the deployment's speed modes. Real SUMO: a
small policy cloned from IDM that wants the road's 20 m/s from vans that can do 10; a policy
at full throttle behind trucks of accel 1.0 (drawn net 300's accelerated at the bound's 2.6
m/s^2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import line_net, small_section_scenario
from deploy_nets import idm_agent
from section_files import routes_file, vtype
from test_drivers import _run

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.deploy.safety import safety_cap
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section

VAN_MAX_MPS = 10.0
LIMIT_MPS = 20.0
TRUCK_ACCEL = 1.0


VAN = vtype(
    "van", length=6, minGap=2.5, accel=2.6, decel=4.5, sigma=0, maxSpeed=VAN_MAX_MPS,
    speedFactor=1, speedDev=0,
)  # fmt: skip
TRUCK = vtype(
    "truck", vClass="truck", length=12, minGap=2.5, accel=TRUCK_ACCEL, decel=4.0, sigma=0,
    maxSpeed=25, speedFactor=1, speedDev=0,
)  # fmt: skip


def _road(folder: Path, limit_mps: float, kind: str, period_s: float, depart_mps: float):
    """(net, routes): one straight lane A -> B (1.5 km, limit ``limit_mps``), a vehicle of
    vType ``kind`` (``VAN``, ``TRUCK``) every ``period_s`` until 40 s at ``depart_mps``."""
    flow = (
        f'<flow id="f" type="{kind}" begin="0" end="40" period="{period_s:g}" '
        f'departSpeed="{depart_mps:g}"><route edges="A B"/></flow>'
    )
    net = line_net(folder, (1000.0, 1500.0), 1, limit_mps)
    return net, routes_file(folder / f"{kind}s.rou.xml", [VAN if kind == "van" else TRUCK], [flow])


def uncapped(slot: str) -> type[SectionSpeedDriver]:
    """The driver as it was before a cap: no maxSpeed (``vmax``) or accel known."""

    class Uncapped(SectionSpeedDriver):
        def take(self, sim, vids) -> None:
            super().take(sim, vids)
            getattr(self.slots, slot)[self.slots.slots(vids)] = np.inf

    return Uncapped


def full_throttle(obs: np.ndarray) -> np.ndarray:
    """A policy that always wants the bound's acceleration (clipped to it: 2.6 m/s^2)."""
    return np.full(len(obs), 10.0)


@pytest.mark.parametrize("safety", ["none", "sumo"])
def test_driven_vans_never_exceed_their_max_speed(tmp_path: Path, safety: str) -> None:
    net, routes = _road(tmp_path, LIMIT_MPS, "van", 6.0, 5.0)  # vans: maxSpeed 10
    sc = small_section_scenario(tmp_path, net, routes, ["A", "B"])
    section = read_section(net, ["A", "B"], False)
    agent = idm_agent("lookahead", LIMIT_MPS)
    top = {}
    for name, cls in (("capped", SectionSpeedDriver), ("uncapped", uncapped("vmax"))):
        drv = cls(sc, section, 0, policy_batch(agent), safety)
        df, stats = _run(sc, drv)
        assert stats["collisions"] == 0 and drv.stats.vehicle_steps_driven > 500
        assert {p.max_speed_mps for p in drv.vtypes.values()} == {VAN_MAX_MPS}  # SUMO's
        top[name] = float(df["speed_mps"].max())
    # What SUMO recorded of every driven van after each step: never above its maxSpeed;
    # the same policy without the cap drives them well above it.
    assert top["capped"] <= VAN_MAX_MPS + 1e-9, top
    assert top["uncapped"] > VAN_MAX_MPS + 2.0, top


@pytest.mark.parametrize("safety", ["none", "sumo"])
def test_driven_trucks_never_accelerate_beyond_their_vtype(tmp_path: Path, safety: str) -> None:
    net, routes = _road(tmp_path, 30.0, "truck", 8.0, 2.0)  # trucks: accel 1.0
    sc = small_section_scenario(tmp_path, net, routes, ["A", "B"])
    section = read_section(net, ["A", "B"], False)
    top = {}
    for name, cls in (("capped", SectionSpeedDriver), ("uncapped", uncapped("accel"))):
        drv = cls(sc, section, 0, full_throttle, safety)
        df, stats = _run(sc, drv)
        assert stats["collisions"] == 0 and drv.stats.vehicle_steps_driven > 300
        assert {p.accel_mps2 for p in drv.vtypes.values()} == {TRUCK_ACCEL}  # SUMO's
        moving = df[df["speed_mps"] < 24.0]  # below maxSpeed: the throttle is what limits
        top[name] = float(moving["accel_mps2"].max())
        assert float(df["speed_mps"].max()) <= 25.0 + 1e-9  # maxSpeed still holds
    # SUMO's recorded accelerations of the driven trucks: never above their accel; the
    # same policy without the cap takes them to the bound.
    assert top["capped"] <= TRUCK_ACCEL + 1e-9, top
    assert top["uncapped"] > 2.0, top


def test_the_safety_layers_floor_stays_at_or_below_max_speed() -> None:
    # A vehicle at 9.5 m/s with no leader on a 60 m/s road: the floor (a fifth of the
    # limit, 12 m/s, at most v + a dt = 10.8) would lift a command of 9 m/s above a
    # maxSpeed of 10 without the bound.
    obs = np.array([[9.5, 60.0, NO_LEADER_GAP_M, 0.0]])
    gap, decel, lead = np.array([NO_LEADER_GAP_M]), np.array([4.5]), np.array([-1])
    cmd = np.array([9.0])
    free, _, raised = safety_cap(cmd, obs, gap, decel, decel, lead, 0.5, 2.6, 0.2)
    assert free[0] == pytest.approx(10.8) and raised == 1
    held, _, _ = safety_cap(
        cmd, obs, gap, decel, decel, lead, 0.5, 2.6, 0.2, vmax=np.array([VAN_MAX_MPS])
    )
    assert held[0] == VAN_MAX_MPS

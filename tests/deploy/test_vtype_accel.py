"""A driven vehicle is held to its vType's accel (its physics, as its maxSpeed): SUMO does
not impose it on a speed command under the deployment's speed modes, and drawn net 300's
trucks (accel 1.0) accelerated at the bound's 2.6 m/s^2. Real SUMO, a policy at full
throttle."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import line_net
from test_drivers import _run, _scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.road.section import read_section

TRUCK_ACCEL = 1.0
LIMIT_MPS = 30.0


def _road(folder: Path) -> tuple[Path, Path]:
    """One straight lane A -> B (1.5 km, limit 30 m/s); trucks (accel 1.0) every 8 s."""
    net = line_net(folder, (1000.0, 1500.0), 1, LIMIT_MPS)
    routes = folder / "trucks.rou.xml"
    routes.write_text(
        "<routes>\n"
        f'    <vType id="truck" vClass="truck" length="12" minGap="2.5" accel="{TRUCK_ACCEL}" '
        'decel="4.0" sigma="0" maxSpeed="25" speedFactor="1.0" speedDev="0"/>\n'
        '    <flow id="f" type="truck" begin="0" end="40" period="8" departSpeed="2">'
        '<route edges="A B"/></flow>\n'
        "</routes>\n"
    )
    return net, routes


def full_throttle(obs: np.ndarray) -> np.ndarray:
    """A policy that always wants the bound's acceleration (clipped to it: 2.6 m/s^2)."""
    return np.full(len(obs), 10.0)


class Uncapped(SectionSpeedDriver):
    """The driver as it was before the cap: no accel known for any vehicle."""

    def take(self, sim, vids) -> None:
        super().take(sim, vids)
        self.slots.accel[self.slots.slots(vids)] = np.inf


@pytest.mark.parametrize("safety", ["none", "sumo"])
def test_driven_trucks_never_accelerate_beyond_their_vtype(tmp_path: Path, safety: str) -> None:
    net, routes = _road(tmp_path)
    sc = _scenario(tmp_path, net, routes, ["A", "B"])
    section = read_section(net, ["A", "B"], False)
    top = {}
    for name, cls in (("capped", SectionSpeedDriver), ("uncapped", Uncapped)):
        drv = cls(sc, section, 0, full_throttle, safety)
        df, stats = _run(sc, drv)
        assert stats["collisions"] == 0 and drv.stats.vehicle_steps_driven > 300
        assert set(drv.accel.values()) == {TRUCK_ACCEL}  # read from SUMO's vType
        moving = df[df["speed_mps"] < 24.0]  # below maxSpeed: the throttle is what limits
        top[name] = float(moving["accel_mps2"].max())
        assert float(df["speed_mps"].max()) <= 25.0 + 1e-9  # maxSpeed still holds
    # SUMO's recorded accelerations of the driven trucks: never above their accel; the
    # same policy without the cap takes them to the bound.
    assert top["capped"] <= TRUCK_ACCEL + 1e-9, top
    assert top["uncapped"] > 2.0, top

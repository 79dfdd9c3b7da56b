"""``scripts/classify_brakings.py``: its hooks classify each emergency braking a real SUMO
deployment counts, and put every wrapped name back. IDM cars (decel 3.0) under a policy
that always brakes at the bound (-4.5 m/s^2, ``test_command_brake``'s road): with
``deploy.command_brake = "bounds"`` every one is the policy's; with "decel" there are none."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT
from test_command_brake import _road
from test_safety import _run_section

from macromicro_sumo.deploy import drivers
from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.simulation import Simulation

sys.path.append(str(ROOT / "scripts"))  # the script imports deploy_runs beside it
_spec = importlib.util.spec_from_file_location(
    "classify_brakings", ROOT / "scripts" / "classify_brakings.py"
)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


@pytest.mark.parametrize("brake", ["bounds", "decel"])
def test_each_emergency_braking_is_classified_and_the_hooks_undone(
    tmp_path: Path, brake: str
) -> None:
    sc = load_scenario(_road(tmp_path, brake))
    before = (drivers.speed_commands, Simulation.set_speeds, drivers.SectionDriver.count_brakings)
    undo = script.install(sc)
    try:
        section = read_section(sc.resolve(sc.network.net_file), ["A", "B"], False)
        a_min = sc.bounds.accel_mps2[0]
        drv = SectionSpeedDriver(sc, section, 0, lambda obs: np.full(len(obs), a_min), "sumo")
        _, stats = _run_section(sc, drv)
    finally:
        undo()
    after = (drivers.speed_commands, Simulation.set_speeds, drivers.SectionDriver.count_brakings)
    assert after == before
    rows = script.REC.rows
    assert len(rows) == drv.stats.emergency_brakings
    if brake == "bounds":
        assert len(rows) > 20
        assert {r["what"] for r in rows} == {"policy"}
        assert all(r["accel_mps2"] < -3.0 for r in rows)
    else:
        assert rows == []

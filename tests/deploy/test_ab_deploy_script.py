"""scripts/ab_deploy.py loads the new variant's deploy modules from another checkout beside
the base package: each imports the variant's modules loaded before it, the base modules in
``sys.modules`` stay the ones every other import gets, and a module missing from the
checkout is one line."""

from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

import pytest
from conftest import ROOT

import macromicro_sumo.deploy.drivers as base_drivers
import macromicro_sumo.deploy.slots as base_slots

_spec = importlib.util.spec_from_file_location("ab_deploy", ROOT / "scripts" / "ab_deploy.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def test_the_new_variant_imports_its_own_modules_and_leaves_the_base_in_place(
    tmp_path: Path,
) -> None:
    # A copy of the package with a marker in its slots module: the new variant's.
    shutil.copytree(ROOT / "macromicro_sumo", tmp_path / "macromicro_sumo")
    slots = tmp_path / "macromicro_sumo" / "deploy" / "slots.py"
    slots.write_text(slots.read_text() + "\nVARIANT = 'new'\n")
    before = dict(sys.modules)
    new = script.variant(tmp_path, ["deploy.slots", "deploy.drivers"])
    new_slots = new["macromicro_sumo.deploy.slots"]
    new_drivers = new["macromicro_sumo.deploy.drivers"]
    assert Path(new_slots.__file__) == slots and new_slots.VARIANT == "new"
    # The new drivers module drives with the new slots, the base one with the base slots.
    assert new_drivers.VehicleSlots is new_slots.VehicleSlots
    assert new_drivers.VehicleSlots is not base_slots.VehicleSlots
    assert base_drivers.VehicleSlots is base_slots.VehicleSlots
    assert sys.modules["macromicro_sumo.deploy.slots"] is base_slots
    assert sys.modules["macromicro_sumo.deploy.drivers"] is base_drivers
    assert {k: v for k, v in sys.modules.items() if k in before} == before


def test_a_module_missing_from_the_new_checkout_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=r"deploy/slots\.py not found"):
        script.variant(tmp_path, ["deploy.slots"])
    assert "macromicro_sumo.deploy.slots" in sys.modules
    assert sys.modules["macromicro_sumo.deploy.slots"] is base_slots


def test_the_default_modules_hold_the_drivers_mixin_before_the_driver() -> None:
    """The default variant is the driver with its slots, observation and merge mixin, each
    loaded before ``deploy.drivers`` imports it (else the base's would run in both arms)."""
    order = list(script.MODULES)
    for m in (
        "deploy.slots",
        "deploy.observe",
        "deploy.merge_yield",
        "deploy.policy_batch",
        "deploy.section_driver",
        "deploy.lane_asks",
        "deploy.driver_observe",
    ):
        assert m in order and order.index(m) < order.index("deploy.drivers"), order
    # road.physics (count_nonzero) before every deploy module that imports it
    assert order[0] == "road.physics", order

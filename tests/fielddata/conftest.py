"""A small simulated ground truth on a random corridor (lane counts change along it), the
source every field-data fixture is exported from."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from macromicro_sumo.cli import main
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.netgen import random_corridor


@pytest.fixture(scope="session")
def field_truth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One 120 s run (0.2 s of SUMO), 30 % instrumented, E1 loops every 200 m, 30 s intervals."""
    folder = tmp_path_factory.mktemp("field_truth")
    cor = random_corridor(folder / "net", 3)
    # tests/conftest.py's dump_toml is out of reach here (this file is a conftest too).
    (folder / "corridor.toml").write_text(
        f"""name = "corridor"
seed = 5

[network]
kind = "sumo"
sumocfg = {json.dumps(str(cor.sumocfg))}

[section]
edges = {json.dumps(list(cor.section_edges))}
closed = false

[instrumented]
penetration = 0.3

[simulation]
warmup_s = 150.0
duration_s = 120.0
n_runs = 1

[detectors]
interval_s = 30.0
auto_spacing_m = 200.0
"""
    )
    assert (
        main(["simulate", str(folder / "corridor.toml"), "--out", str(folder / "gt"), "--quiet"])
        == 0
    )
    return folder / "gt"


@pytest.fixture(scope="session")
def section(field_truth: Path) -> Section:
    return Section.read(field_truth / "section.json")


@pytest.fixture(scope="session")
def observed(field_truth: Path) -> pd.DataFrame:
    traj = pd.read_csv(field_truth / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    return traj[traj["observed"]].reset_index(drop=True)


@pytest.fixture(scope="session")
def detectors(field_truth: Path) -> pd.DataFrame:
    return pd.read_csv(field_truth / "detectors.csv", dtype={"detector_id": str})

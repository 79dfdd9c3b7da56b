"""scripts/bench_generator.py keeps working: its rings have the paper ring's density, and
one small measurement runs every stage it times (real SUMO and torch)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
from conftest import ROOT

from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section

sys.path.insert(0, str(ROOT / "scripts"))  # as when run: it imports its sibling scripts
_spec = importlib.util.spec_from_file_location(
    "bench_generator", ROOT / "scripts" / "bench_generator.py"
)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_rings_have_the_paper_density(tmp_path: Path) -> None:
    sc = load_scenario(bench.ring_scenario(tmp_path, 7, 2))
    section = load_section(sc)[1]
    assert sc.fleet.n_vehicles == 7 and section.closed and section.max_lanes == 1
    assert math.isclose(section.length_m, 7 * 2 * math.pi * 100.0 / 5, abs_tol=1e-3)


def test_one_small_measurement(tmp_path: Path) -> None:
    args = bench.get_options(["--n", "5", "--epochs", "1", "--runs", "2", "--env-steps", "20"])
    args.repeats = 1
    row = bench.measure(5, args, tmp_path)
    for key in ("epoch_s", "complete_k4_s", "complete_share_s", "env_us"):
        assert np.isfinite(row[key]) and row[key] > 0, key
    assert row["projected_k4"] >= 0

"""Sweeps over the optional tables of a section scenario (issue 16, item 6b): the ring's
demand as a section's ([fleet], [speed_limits], [initial]) is swept like any other key, and
runs; a file without those tables refuses their keys for the whole batch."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT, assert_one_line_error, dump_toml

from macromicro_sumo.batch.sweep import expand
from macromicro_sumo.cli import main
from macromicro_sumo.errors import UserError

RING_SECTION = ROOT / "scenarios" / "ring_paper_section.toml"
CORRIDOR = ROOT / "scenarios" / "netgen_corridor.toml"


def with_sweep(src: Path, path: Path, sweep: str, **simulation) -> Path:
    """``src`` with its network's files by absolute path, ``simulation`` keys set and a
    ``[sweep]`` table."""
    table = tomllib.loads(src.read_text())
    table.pop("sweep", None)
    net = table["network"]
    for key in ("net_file", "sumocfg"):
        if key in net:
            net[key] = str((src.parent / net[key]).resolve())
    for key in ("additional_files", "route_files"):
        if key in net:
            net[key] = [str((src.parent / p).resolve()) for p in net[key]]
    table["simulation"].update(simulation)
    path.write_text(dump_toml(table) + "\n[sweep]\n" + sweep.strip() + "\n")
    return path


def test_a_sweep_over_fleet_keys_expands_and_each_variant_has_its_values(tmp_path):
    path = with_sweep(
        RING_SECTION,
        tmp_path / "ring.toml",
        """
        fleet.n_vehicles = [4, 5]
        speed_limits.range_mps = [[12.0, 13.0], [13.0, 14.0]]
        spacing_concentration = [5.0]
        """,
    )
    variants = expand([path])
    assert [v.error for v in variants] == [""] * 4
    assert variants[0].name == (
        "fleet.n_vehicles=4__speed_limits.range_mps=12_13__spacing_concentration=5"
    )
    for v in variants:
        sc = v.scenario
        assert sc.fleet.n_vehicles == v.params["fleet.n_vehicles"]
        assert list(sc.speed_limits.range_mps) == v.params["speed_limits.range_mps"]
        # the short key resolved into [initial], the only table with it
        assert sc.initial.spacing_concentration == v.params["initial.spacing_concentration"] == 5.0
        assert sc.fleet.length_m == 5.0  # the keys not swept are the file's
    assert {v.scenario.fleet.n_vehicles for v in variants} == {4, 5}


@pytest.mark.slow  # the fleet keys' expansion is tested above; batch runs in tests/batch/test_batch.py
def test_a_fleet_sweep_runs_each_variant_with_its_fleet(tmp_path):
    """``batch --stage simulate``: each variant's ground truth drives its own fleet size
    within its own limits (2 runs of 60 s each)."""
    path = with_sweep(
        RING_SECTION,
        tmp_path / "ring.toml",
        """
        fleet.n_vehicles = [3, 4]
        speed_limits.range_mps = [[12.0, 12.5]]
        """,
        n_runs=2,
        duration_s=60.0,
    )
    out = tmp_path / "out"
    code = main(["batch", str(path), "--out", str(out), "--stage", "simulate", "--quiet"])
    assert code == 0
    for n in (3, 4):
        gt = out / "variants" / f"fleet.n_vehicles={n}__speed_limits.range_mps=12_12.5"
        gt = next(gt.rglob("trajectories.csv")).parent
        traj = pd.read_csv(gt / "trajectories.csv")
        assert (traj.groupby(["run", "time_s"])["vehicle_id"].nunique() == n).all()
        limits = pd.read_csv(gt / "speed_limits.csv")["speed_limit_mps"]
        assert limits.between(12.0, 12.5).all()


@pytest.mark.parametrize(
    ("src", "sweep", "fragments"),
    [
        (
            RING_SECTION,
            "fleet.n_vehicle = [4]",
            [
                "unknown sweep key 'fleet.n_vehicle'",
                "accepted keys of [fleet]: fleet.n_vehicles, fleet.length_m",
                "fleet.max_speed_mps",
                "did you mean fleet.n_vehicles",
            ],
        ),
        (RING_SECTION, "min_gap_m = [2.0]", ["ambiguous", "bounds.min_gap_m", "fleet.min_gap_m"]),
        (RING_SECTION, "initial = [1]", ["'initial' is a table", "initial.speed_mps"]),
        (
            CORRIDOR,
            "fleet.n_vehicles = [5]",
            ["unknown sweep key 'fleet.n_vehicles'", "[fleet], [initial], [speed_limits] only"],
        ),
        (CORRIDOR, "range_mps = [[12.0, 14.0]]", ["unknown sweep key 'range_mps'"]),
    ],
)
def test_bad_optional_table_keys_are_one_line_errors_naming_accepted_keys(
    tmp_path, capsys, src, sweep, fragments
):
    path = with_sweep(src, tmp_path / "bad.toml", sweep)
    code = main(["batch", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    assert_one_line_error(capsys, code, str(path), *fragments)
    assert not (tmp_path / "out" / "variants").exists()


def test_a_short_key_counts_only_the_files_own_optional_tables(tmp_path):
    # Without [fleet], min_gap_m is the section's bounds.min_gap_m, as before the fleet keys.
    path = with_sweep(CORRIDOR, tmp_path / "c.toml", "min_gap_m = [1.0, 2.5]")
    variants = expand([path])
    assert [v.params for v in variants] == [{"bounds.min_gap_m": 1.0}, {"bounds.min_gap_m": 2.5}]
    assert [v.scenario.bounds.min_gap_m for v in variants] == [1.0, 2.5]
    with pytest.raises(UserError, match="sweep key 'min_gap_m' is ambiguous"):
        expand([with_sweep(RING_SECTION, tmp_path / "r.toml", "min_gap_m = [2.0]")])


def test_a_sweep_over_a_key_the_scenario_never_reads_is_refused(tmp_path):
    """A ring file read as its section drops the ring's fixed speed bounds: sweeping them
    would run one scenario twice and report no sensitivity. The batch says so instead."""
    table = tomllib.loads((ROOT / "scenarios" / "ring_paper.toml").read_text())
    table.pop("sweep", None)
    table["network"]["net_file"] = str(
        (ROOT / "scenarios" / table["network"]["net_file"]).resolve()
    )
    table["network"]["routes_file"] = str(
        (ROOT / "scenarios" / table["network"]["routes_file"]).resolve()
    )
    path = tmp_path / "ring.toml"
    sweep = "[sweep]\nbounds.speed_mps = [[10.0, 14.0], [9.0, 15.0]]\n"
    path.write_text('road = "section"\n' + dump_toml(table) + "\n" + sweep)
    with pytest.raises(UserError) as err:
        expand([path])
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{path}: [sweep] variants ")
    assert "load to the same scenario: bounds.speed_mps has no effect" in msg

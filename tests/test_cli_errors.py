"""Bad input through ``macromicro simulate``: exit code 2, one line naming the file, the
key and the accepted range, no traceback, and no files in the output folder."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from conftest import NETS, listing

from macromicro_sumo.cli import main


def simulate_fails(
    capsys: pytest.CaptureFixture[str], scenario: Path, out: Path, *fragments: str
) -> str:
    """Run the CLI expecting a user error; return its message."""
    if not out.exists():
        out.mkdir()
    before = listing(out) if out.is_dir() else out.read_bytes()
    code = main(["simulate", str(scenario), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    assert err.startswith("error: ") and err.endswith("\n") and err.count("\n") == 1, err
    for fragment in fragments:
        assert fragment in err, f"{fragment!r} not in {err!r}"
    after = listing(out) if out.is_dir() else out.read_bytes()
    assert after == before, "the output folder changed"
    return err


@pytest.fixture
def out(tmp_path: Path) -> Path:
    return tmp_path / "out"


def test_malformed_toml(capsys, tmp_path, out):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "ring"\n[network\nradius_m = 100\n')
    simulate_fails(capsys, bad, out, str(bad), "malformed TOML", "line 2")


def test_missing_scenario_file(capsys, tmp_path, out):
    missing = tmp_path / "nope.toml"
    simulate_fails(capsys, missing, out, str(missing), "not found")


def test_unknown_key(capsys, make_scenario, out):
    path = make_scenario({"fleet.colour": "red"})
    simulate_fails(capsys, path, out, str(path), "[fleet]", "'colour'", "n_vehicles")


def test_missing_required_key(capsys, make_scenario, out):
    path = make_scenario(drop=("fleet.n_vehicles",))
    simulate_fails(capsys, path, out, str(path), "'fleet.n_vehicles'", "missing")


def test_wrong_type(capsys, make_scenario, out):
    path = make_scenario({"simulation.duration_s": "long"})
    simulate_fails(capsys, path, out, str(path), "simulation.duration_s", "[1, 1e+06]")


def test_negative_radius(capsys, make_scenario, out):
    path = make_scenario({"network.radius_m": -100.0})
    simulate_fails(capsys, path, out, str(path), "network.radius_m", "-100", "(0, 1e5]")


def test_fewer_than_two_vehicles(capsys, make_scenario, out):
    path = make_scenario({"fleet.n_vehicles": 1})
    simulate_fails(capsys, path, out, str(path), "fleet.n_vehicles", "[2, 10000]")


def test_speed_bounds_reversed(capsys, make_scenario, out):
    path = make_scenario({"bounds.speed_mps": [14.0, 10.5]})
    simulate_fails(capsys, path, out, str(path), "bounds.speed_mps", "reversed", "[0, 100]")


def test_missing_network_file(capsys, make_scenario, tmp_path, out):
    missing = tmp_path / "nets" / "ring.net.xml"
    path = make_scenario({"network.net_file": str(missing)})
    simulate_fails(capsys, path, out, str(path), "network.net_file", str(missing), "not exist")


def test_relative_network_file_resolves_from_the_scenario(capsys, make_scenario, tmp_path, out):
    path = make_scenario({"network.net_file": "ring.net.xml"})
    simulate_fails(capsys, path, out, "network.net_file", str(tmp_path / "ring.net.xml"))


def test_network_file_that_is_not_a_network(capsys, make_scenario, tmp_path, out):
    junk = tmp_path / "junk.net.xml"
    junk.write_text("this is not XML")
    path = make_scenario({"network.net_file": str(junk)})
    simulate_fails(capsys, path, out, str(junk), "not a readable SUMO network")


def test_network_that_does_not_match_the_radius(capsys, make_scenario, out):
    path = make_scenario(
        {
            "network.net_file": str(NETS / "ring_r36.6_e4.net.xml"),
            "network.routes_file": str(NETS / "ring_r36.6_e4.add.xml"),
        }
    )
    simulate_fails(capsys, path, out, "ring_r36.6_e4.net.xml", "radius_m = 100")


def test_output_folder_is_a_file(capsys, make_scenario, tmp_path):
    out_file = tmp_path / "out.csv"
    out_file.write_text("keep me\n")
    scenario = make_scenario()
    siblings = listing(tmp_path)
    simulate_fails(capsys, scenario, out_file, str(out_file), "existing file")
    assert out_file.read_text() == "keep me\n"
    assert listing(tmp_path) == siblings


# --------------------------------------------------------------------------- SUMO's file lists


def test_network_file_in_a_folder_with_a_comma(capsys, make_scenario, tmp_path, out):
    """SUMO splits every file option at commas: such a path is refused, naming it."""
    nets = tmp_path / "nets,v2"
    nets.mkdir()
    for name in ("ring_r100_e4.net.xml", "ring_r100_e4.det.add.xml"):
        shutil.copy(NETS / name, nets / name)
    path = make_scenario({"network.net_file": str(nets / "ring_r100_e4.net.xml")})
    simulate_fails(capsys, path, out, str(nets / "ring_r100_e4.net.xml"), "comma")


def test_out_with_a_comma(capsys, make_scenario, tmp_path):
    out = tmp_path / "results,2024"
    simulate_fails(capsys, make_scenario(), out, f"--out: {out} has a comma")


def test_an_obviously_huge_scenario_is_refused_with_its_estimate(capsys, make_scenario, out):
    path = make_scenario({"simulation.n_runs": 10_000, "simulation.duration_s": 1e6})
    simulate_fails(
        capsys,
        path,
        out,
        "trajectory rows per run",
        "x simulation.n_runs = 10000 need about",
        "lower simulation.duration_s or n_runs",
    )

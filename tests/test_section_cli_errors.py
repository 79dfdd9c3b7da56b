"""Bad input on a section scenario: one `error:` line naming file and element, exit 2,
no traceback, and no output folder left behind."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from conftest import ROOT, dump_toml

from macromicro_sumo.cli import main

CORRIDOR = ROOT / "sumo_nets" / "netgen_corridor"
EDGES = ["e0", "e1", "e2", "e3", "e4", "e5", "e6"]


@pytest.fixture
def files(tmp_path: Path) -> Path:
    """A private copy of the corridor example (net, routes) to break."""
    for name in ("corridor.net.xml", "corridor.rou.xml"):
        shutil.copy(CORRIDOR / name, tmp_path / name)
    return tmp_path


def scenario(folder: Path, **tables: dict) -> Path:
    table = {
        "name": "bad",
        "network": {
            "kind": "sumo",
            "net_file": str(folder / "corridor.net.xml"),
            "route_files": [str(folder / "corridor.rou.xml")],
        },
        "section": {"edges": EDGES},
        "simulation": {"warmup_s": 10.0, "duration_s": 60.0, "n_runs": 2},
    }
    for name, sub in tables.items():
        table.setdefault(name, {}).update(sub)
    path = folder / "bad.toml"
    path.write_text(dump_toml(table))
    return path


def fails(capsys: pytest.CaptureFixture, path: Path, *needles: str) -> str:
    out = path.parent / "out"
    assert main(["simulate", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    assert not out.exists()
    return err


def test_net_file_that_is_not_sumo_xml(capsys, files: Path) -> None:
    (files / "corridor.net.xml").write_text("<routes/>\n")
    fails(capsys, scenario(files), "corridor.net.xml", "not a SUMO network", "<routes>")


def test_route_with_a_missing_edge(capsys, files: Path) -> None:
    rou = files / "corridor.rou.xml"
    rou.write_text(
        rou.read_text().replace('"e0 ', '"e0 nowhere ', 1).replace('"e0"', '"nowhere"', 1)
    )
    err = fails(capsys, scenario(files), "corridor.rou.xml", "nowhere")
    assert "not in" in err


def test_disconnected_section(capsys, files: Path) -> None:
    fails(capsys, scenario(files, section={"edges": ["e0", "e2"]}), "'e0' -> 'e2'", "not connected")


def test_section_edge_not_in_the_network(capsys, files: Path) -> None:
    fails(capsys, scenario(files, section={"edges": ["e0", "e9"]}), "'e9'", "corridor.net.xml")


def test_vtype_with_a_bad_length(capsys, files: Path) -> None:
    """A missing length is SUMO's default for the vClass (tests/sumo); a bad one is refused."""
    rou = files / "corridor.rou.xml"
    rou.write_text(rou.read_text().replace('length="4.5"', 'length="-4.5"', 1))
    fails(capsys, scenario(files), "corridor.rou.xml", "vType 'car_idm' has length '-4.5'")


def test_detector_file_for_another_network(capsys, files: Path) -> None:
    add = files / "loops.add.xml"
    add.write_text(
        '<additional><inductionLoop id="d1" lane="gneE7_0" pos="5" period="60" file="o.xml"/>'
        "</additional>\n"
    )
    path = scenario(files, network={"additional_files": [str(add)]})
    fails(capsys, path, "loops.add.xml", "'d1'", "gneE7_0", "another network")


@pytest.mark.parametrize("rate", [0.0, 1.5, -0.1, float("nan"), float("inf")])
def test_penetration_outside_0_1(capsys, files: Path, rate: float) -> None:
    fails(capsys, scenario(files, instrumented={"penetration": rate}), "penetration", "(0, 1]")


def test_no_detectors_and_placement_off(capsys, files: Path) -> None:
    path = scenario(files, detectors={"auto_spacing_m": 0.0})
    fails(capsys, path, "auto_spacing_m = 0", "no detector")


def test_unknown_network_kind(capsys, files: Path) -> None:
    fails(capsys, scenario(files, network={"kind": "osm"}), "network.kind", "'ring', 'sumo'")


def test_instrumented_vtype_not_in_the_demand(capsys, files: Path) -> None:
    fails(capsys, scenario(files, instrumented={"vtype": "truck"}), "instrumented.vtype", "'truck'")


def test_several_completions_per_scene_name_their_replacement(capsys, files: Path) -> None:
    path = scenario(files, evaluation={"completions_per_scene": 4})
    fails(capsys, path, "evaluation.completions_per_scene", "generator.eval_completions")


def test_route_file_without_vehicles(capsys, files: Path) -> None:
    """Routes and vTypes but nothing that drives them (was: `min() arg is an empty sequence`)."""
    rou = files / "corridor.rou.xml"
    rou.write_text("".join(ln for ln in rou.read_text().splitlines(True) if "<flow" not in ln))
    fails(capsys, scenario(files), "corridor.rou.xml", "no vehicle, trip or flow")


def test_route_file_in_a_folder_with_a_comma(capsys, files: Path) -> None:
    """SUMO would open 'a' and 'b/corridor.rou.xml' for 'a,b/corridor.rou.xml'."""
    odd = files / "demand,v2"
    odd.mkdir()
    shutil.move(files / "corridor.rou.xml", odd / "corridor.rou.xml")
    path = scenario(files, network={"route_files": [str(odd / "corridor.rou.xml")]})
    fails(capsys, path, str(odd / "corridor.rou.xml"), "has a comma", "rename or move")


def test_unknown_instrumented_ids(capsys, files: Path) -> None:
    """Ids are checked against the demand before SUMO starts: a vehicle or trip id, or a
    flow's ``<flow id>.<n>``."""
    path = scenario(files, instrumented={"ids": ["f_idm.0", "f_krauss.12", "f_idm.x", "ghost"]})
    fails(capsys, path, "instrumented.ids names 'f_idm.x'", "f_idm.<n>", "f_krauss.<n>")


def test_a_ground_truth_that_will_not_fit_in_memory(capsys, files: Path, monkeypatch) -> None:
    """A section's vehicle count is known once SUMO runs: the first rows project the need."""
    monkeypatch.setattr("macromicro_sumo.files.memory_limit_bytes", lambda: 4096)
    path = scenario(files)
    out = files / "out"
    assert main(["simulate", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err, err
    assert "trajectory rows per run (as run 0 goes) x simulation.n_runs = 2" in err, err
    assert "of memory, more than the 0.0 GiB of this machine" in err, err
    assert list(out.iterdir()) == []

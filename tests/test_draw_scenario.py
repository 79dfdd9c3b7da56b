"""scripts/draw_scenario.py writes a scenario the tool loads, on the net its seed draws, and
refuses a folder that holds anything (it never writes over what it did not write)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from conftest import ROOT

from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section

sys.path.insert(0, str(ROOT / "scripts"))  # as when run: it imports its sibling scripts
_spec = importlib.util.spec_from_file_location(
    "draw_scenario", ROOT / "scripts" / "draw_scenario.py"
)
draw = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(draw)


def test_a_drawn_motorway_loads_with_the_examples_settings(tmp_path: Path, capsys) -> None:
    assert draw.main(["--seed", "501", "--out", str(tmp_path / "d")]) == 0
    path = Path(capsys.readouterr().out.strip())
    sc = load_scenario(path)
    assert sc.name == "k501" and sc.simulation.n_runs == 4
    assert sc.policy.prior == "krauss" and sc.policy.driver_speed == "memory"
    section = load_section(sc)[1]
    # 501 is the 4-2-1-1-4 main line docs/deploy.md measures as "drawn 501"
    assert list(section.edge_ids) == ["m0", "m1", "m2", "m3", "m4"]
    assert section.n_lanes.tolist() == [4, 2, 1, 1, 4]


def test_a_drawn_arterial_keeps_its_signal_cycle_intervals(tmp_path: Path, capsys) -> None:
    assert (
        draw.main(["--seed", "731", "--kind", "arterial", "--variant", "d", "--out", str(tmp_path)])
        == 0
    )
    sc = load_scenario(Path(capsys.readouterr().out.strip()))
    assert sc.name == "d731" and sc.detectors.interval_s == 90.0
    assert sc.policy.prior != "krauss"


def test_a_folder_with_files_is_refused(tmp_path: Path, capsys) -> None:
    (tmp_path / "mine.txt").write_text("keep")
    assert draw.main(["--seed", "501", "--out", str(tmp_path)]) == 2
    assert "not empty" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["mine.txt"]


def test_a_negative_seed_is_one_line_and_writes_nothing(tmp_path: Path, capsys) -> None:
    out = tmp_path / "d"
    assert draw.main(["--seed", "-1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--seed -1" in err and "[0, 2**32)" in err
    assert not out.exists()

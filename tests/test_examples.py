"""The example scenarios and networks ship with the package: a wheel carries them, they
resolve from any folder once installed, and `--example NAME` runs one."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

from macromicro_sumo.cli import main
from macromicro_sumo.env.examples import example_names, example_scenario, examples_root
from macromicro_sumo.scenario.load import load_scenario

ROOT = Path(__file__).resolve().parents[1]
# What a source distribution is built from (MANIFEST.in adds scenarios/ and sumo_nets/).
SOURCES = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md")
TREES = ("macromicro_sumo", "scenarios", "sumo_nets")


def test_examples_resolve_in_the_checkout():
    assert examples_root() == ROOT  # an editable install reads the repository's folders
    assert {"ring_paper", "netgen_corridor", "highway_bremen"} <= set(example_names())
    for name in example_names():
        sc = load_scenario(example_scenario(name), allow_sweep=True)
        assert Path(sc.source).is_relative_to(ROOT)


def test_example_option_errors_are_one_line(tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main(["run", "--example", "nope", "--out", out]) == 2
    assert "no example scenario 'nope'; accepted: one of" in capsys.readouterr().err
    paper = str(example_scenario("ring_paper"))
    assert main(["simulate", paper, "--example", "ring_paper", "--out", out]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["run", "--out", out]) == 2
    assert "--example NAME for a shipped one (" in capsys.readouterr().err


def _build(cmd: str, cwd: Path) -> str:
    code = f"from setuptools import build_meta as b; print(b.{cmd})"
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, check=True
    )
    return res.stdout.strip().splitlines()[-1]


INSTALLED_CHECK = """
import functools
import sys
from pathlib import Path
import macromicro_sumo
from macromicro_sumo import cli
from macromicro_sumo.cli import main
from macromicro_sumo.env.examples import examples_root, example_scenario
from macromicro_sumo.scenario.load import load_scenario
site = Path(sys.argv[1])
SMALL = {"simulation.n_runs": 2, "simulation.duration_s": 60.0}
assert Path(macromicro_sumo.__file__).is_relative_to(site), macromicro_sumo.__file__
assert examples_root() == site / "macromicro_sumo" / "examples", examples_root()
sc = load_scenario(example_scenario("ring_paper"))
assert sc.resolve(sc.network.net_file).is_relative_to(site)
# The command line's own path with a smaller budget: the paper's 40 runs of 180 s cost 16 s
# of CPU to show what 2 runs of 60 s show (SUMO runs the installed network files).
cli.load_scenario = functools.partial(load_scenario, overrides=SMALL)
assert main(["simulate", "--example", "ring_paper", "--out", "gt", "--quiet"]) == 0
assert main(["doctor"]) == 0
"""


def test_wheel_ships_the_examples_and_they_resolve_once_installed(tmp_path):
    """sdist -> wheel -> unpacked as site-packages; run from an unrelated folder."""
    src = tmp_path / "src"
    src.mkdir()
    for name in SOURCES:
        shutil.copy2(ROOT / name, src / name)
    for name in TREES:
        shutil.copytree(
            ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
        )
    dist = tmp_path / "dist"
    sdist = _build(f"build_sdist({str(dist)!r})", src)
    with tarfile.open(dist / sdist) as tar:
        names = tar.getnames()
        assert any(n.endswith("/scenarios/ring_paper.toml") for n in names)
        assert any(n.endswith("/sumo_nets/ring_r100_e4.net.xml") for n in names)
        tar.extractall(tmp_path / "unpacked", filter="data")
    wheel = _build(f"build_wheel({str(dist)!r})", tmp_path / "unpacked" / sdist[: -len(".tar.gz")])
    site = tmp_path / "site"
    with zipfile.ZipFile(dist / wheel) as whl:
        shipped = set(whl.namelist())
        whl.extractall(site)
    for rel in (
        "scenarios/ring_paper.toml",
        "scenarios/netgen_corridor.toml",
        "sumo_nets/ring_r100_e4.net.xml",
        "sumo_nets/netgen_corridor/corridor.sumocfg",
    ):
        assert f"macromicro_sumo/examples/{rel}" in shipped, rel
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    res = subprocess.run(
        [sys.executable, "-c", INSTALLED_CHECK, str(site)],
        cwd=elsewhere,
        env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)},
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    assert (elsewhere / "gt" / "manifest.json").is_file()
    runs = (elsewhere / "gt" / "runs.csv").read_text().splitlines()
    assert len(runs) == 3, runs  # the header and the two runs asked for


@pytest.mark.parametrize("command", ["simulate", "run"])
def test_example_option_is_in_the_help(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    assert "--example NAME" in capsys.readouterr().out

"""scripts/bench_deploy.py times the actor the scenario's deployment drives with
(``deploy.actor_dtype``) unless told another; its straight-road curve (issue 17: per-vehicle
cost against the number of vehicles) runs in real SUMO with the policy in the loop."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import re
from pathlib import Path

import pytest
from conftest import ROOT

from macromicro_sumo.scenario.load import load_scenario

_spec = importlib.util.spec_from_file_location("bench_deploy", ROOT / "scripts" / "bench_deploy.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def _bench(tmp_path: Path, *extra: str) -> str:
    out = io.StringIO()
    args = ["--skip-bremen", "--sizes", "50", "--steps", "3", "--road-repeats", "1", "--cpu"]
    args += ["--checkpoint", str(tmp_path / "none.pt"), *extra]
    with contextlib.redirect_stdout(out):
        assert script.main(args) == 0
    return out.getvalue()


@pytest.mark.parametrize("extra", [(), ("--actor-dtype", "float64"), ("--actor-float32",)])
def test_the_actor_is_the_scenarios_unless_told_and_the_curve_is_printed(
    tmp_path: Path, extra: tuple[str, ...]
) -> None:
    got = _bench(tmp_path, *extra)
    default = load_scenario(ROOT / "scenarios" / "highway_bremen.toml").deploy.actor_dtype
    want = {(): default, ("--actor-float32",): "float32"}.get(extra, "float64")
    assert f"(actor in {want})" in got, got
    # One size: a row of 50 vehicles, nearly all driven (an instrumented one is SUMO's), both
    # costs positive, and the flatness line.
    row = re.search(r"^\s+50\s+(\d+)\s+([\d.]+)\s+([\d.]+)", got, re.M)
    assert row is not None and 45 <= int(row[1]) <= 50, got
    assert float(row[2]) > 0 and float(row[3]) > 0, got
    assert "largest / smallest over the sizes: 1.00" in got, got


def test_an_unknown_dtype_is_refused() -> None:
    with pytest.raises(SystemExit), contextlib.redirect_stderr(io.StringIO()) as err:
        script.main(["--actor-dtype", "float16"])
    assert "invalid choice: 'float16'" in err.getvalue()

"""scripts/bench_recorder.py on a real Bremen run (the example's demand, run 0, 400 steps):
every per-step call of the recorder timed, and each vehicle's instrumented draw taken after
the run equal to the draw between SUMO's steps (the script checks it and raises)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from conftest import ROOT

_spec = importlib.util.spec_from_file_location(
    "bench_recorder", ROOT / "scripts" / "bench_recorder.py"
)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def test_the_recorders_calls_are_timed_and_the_draws_agree(tmp_path: Path, capsys) -> None:
    sc = script.bench.bremen_scenario(tmp_path)
    parts, steps, draws = script.one_run(sc, 400)
    assert steps == 400 and draws > 50  # vehicles departed: draws on both sides
    assert set(parts) == {*script.PARTS, *script.DRAWS}
    assert all(parts[p] > 0 for p in (*script.PARTS, *script.DRAWS))
    assert script.main(["--repeats", "1", "--steps", "50"]) == 0
    out = capsys.readouterr().out
    assert "50 steps" in out and "draws after the run" in out

"""Stages side by side in worker processes (``pipeline.parallel``): who runs where, what a
failure does, and (slow) that a whole run's outputs are those of the serial run."""

from __future__ import annotations

import json
import os
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from fleet_scenarios import small_fleet_table, write_fleet_scenario

from macromicro_sumo.files import write_json, writer_session
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.pipeline import build
from macromicro_sumo.pipeline.build import SECTION, Stage, run_pipeline, run_stages
from macromicro_sumo.pipeline.parallel import can_ship
from macromicro_sumo.scenario.load import load_scenario


def _write_stage(sc, name: str, manifest: Path, fail: bool = False) -> None:
    """A stand-in stage (module level: a worker can import it): its manifest and its pid."""
    if fail:
        raise ValueError(f"{name} failed on purpose")
    manifest.parent.mkdir(parents=True, exist_ok=True)
    (manifest.parent / f"{name}.pid").write_text(str(os.getpid()))
    write_json(build_manifest(sc, "", name), manifest)


def _stages(sc, out: Path, fail: str = "") -> list[Stage]:
    """a -> (b, c side by side) -> d, b and c writing into the same folder (as the policy
    and its ablations do)."""

    def stage(name: str, folder: str, needs: tuple[str, ...] = ()) -> Stage:
        manifest = out / folder / f"{name}_manifest.json"
        return Stage(name, manifest, partial(_write_stage, sc, name, manifest, name == fail), needs)

    return [
        stage("a", "first"),
        stage("b", "both", ("a",)),
        stage("c", "both", ("a",)),
        stage("d", "last", ("b", "c")),
    ]


def _pid(out: Path, folder: str, name: str) -> int:
    return int((out / folder / f"{name}.pid").read_text())


def test_stages_that_do_not_read_each_other_run_in_workers(make_scenario, tmp_path) -> None:
    sc, out = load_scenario(make_scenario()), tmp_path / "run"
    with writer_session():
        manifest = run_stages(sc, _stages(sc, out), out, "", False, jobs=2)
    me = os.getpid()
    assert _pid(out, "first", "a") == me and _pid(out, "last", "d") == me  # alone: here
    b, c = _pid(out, "both", "b"), _pid(out, "both", "c")
    assert me not in (b, c) and b != c  # side by side, one worker each
    assert list(manifest["timings_s"]) == ["a", "b", "c", "d"]
    assert set(manifest["cpu_s"]) == {"a", "b", "c", "d"}
    # Done: a second call skips every stage; serial (jobs = 1) everything runs here.
    with writer_session():
        again = run_stages(sc, _stages(sc, out), out, "", False, jobs=2)
    assert again["cpu_s"] == {}
    serial = tmp_path / "serial"
    with writer_session():
        run_stages(sc, _stages(sc, serial), serial, "", False, jobs=1)
    assert {_pid(serial, f, n) for f, n in [("both", "b"), ("both", "c")]} == {me}


@pytest.mark.slow  # spawns workers again (seconds each on a loaded machine)
def test_a_failed_worker_stage_fails_the_run_and_keeps_the_others(make_scenario, tmp_path):
    sc, out = load_scenario(make_scenario()), tmp_path / "run"
    with pytest.raises(ValueError, match="c failed on purpose"), writer_session():
        run_stages(sc, _stages(sc, out, fail="c"), out, "", False, jobs=2)
    assert (out / "both" / "b_manifest.json").is_file()  # b finished beside it
    assert not (out / "last").exists()  # d, which reads c, never ran


def test_a_stage_a_worker_cannot_import_runs_here(make_scenario, tmp_path) -> None:
    sc, out = load_scenario(make_scenario()), tmp_path / "run"
    stages = _stages(sc, out)
    closure = stages[2].run
    stages[2] = Stage("c", stages[2].manifest, lambda: closure(), ("a",))
    assert not can_ship(stages[2].run) and can_ship(stages[1].run)
    with writer_session():
        run_stages(sc, stages, out, "", False, jobs=2)
    assert _pid(out, "both", "c") == _pid(out, "both", "b") == os.getpid()


def test_the_pipelines_own_stages_can_go_to_a_worker(make_scenario, tmp_path, monkeypatch):
    """What a worker needs of ``run_pipeline``'s real stages that run side by side (the
    policies, the evaluation, the deployment): each pickles (module-level functions and
    partials of plain arguments). The default run's pipelines run one stage after the other
    (conftest.py); their run in workers is the slow test below."""
    seen: dict[str, bool] = {}

    def record(sc, stages, out, command, progress, jobs=1):
        seen.update({s.name: can_ship(s.run) for s in stages})
        return {}

    monkeypatch.setattr(build, "run_stages", record)
    monkeypatch.setattr(build, "write_report", lambda *args: None)
    with writer_session():
        run_pipeline(load_scenario(make_scenario()), SECTION, tmp_path / "run", "", False)
    side = ["train_policy", "train_policy_micro_only", "train_policy_macro_only"]
    side += ["evaluate", "deploy"]
    assert {name: seen.get(name) for name in side} == dict.fromkeys(side, True), seen


@pytest.mark.slow
def test_a_run_side_by_side_writes_the_serial_runs_outputs(tmp_path) -> None:
    """Real stages (the small fleet on the ring as a section): policies, evaluation and
    deployment in two processes give the serial run's files (the detector-fitted IDM aside:
    its fit stops at a wall-clock budget)."""
    table = small_fleet_table(4, deploy={"methods": ["policy", "idm_calibrated"]})
    sc = load_scenario(write_fleet_scenario(tmp_path, table))
    runs = {}
    for jobs in (1, 2):
        runs[jobs] = tmp_path / f"jobs{jobs}"
        with writer_session():
            run_pipeline(sc, SECTION, runs[jobs], "", False, jobs=jobs)
    one, two = runs[1], runs[2]
    for name in ("policy.pt", "policy_micro_only.pt", "policy_macro_only.pt"):
        a = torch.load(one / "policy" / name, weights_only=True)["state_dict"]
        b = torch.load(two / "policy" / name, weights_only=True)["state_dict"]
        assert all(torch.equal(a[k], b[k]) for k in a), name
    tables = [p.relative_to(one) for p in sorted(one.glob("evaluation/*.csv"))]
    tables += [p.relative_to(one) for p in sorted(one.glob("deploy/*.csv"))]
    assert len(tables) >= 6
    for rel in tables:
        pd.testing.assert_frame_equal(pd.read_csv(one / rel), pd.read_csv(two / rel), obj=rel)
    cpu = json.loads((two / "manifest.json").read_text())["cpu_s"]
    assert np.isfinite(list(cpu.values())).all() and cpu["evaluate"] > 0

"""``macromicro batch`` against real SUMO: sweeps, failed variants, a killed worker, a killed
batch and its re-run, Ctrl-C, and the same bytes from every backend and worker count."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from conftest import ROOT, dump_toml, scenario_table

from macromicro_sumo.batch import runner as batch
from macromicro_sumo.batch.runner import expand, run_batch
from macromicro_sumo.cli import main
from macromicro_sumo.errors import UserError

TINY = {"simulation.n_runs": 1, "simulation.duration_s": 60.0}


def write_sweep(
    path: Path, sweep: str, overrides: dict[str, Any] | None = None, name: str = "sweep"
) -> Path:
    """A copy of the paper scenario (``overrides`` applied) with a ``[sweep]`` table."""
    table = scenario_table({**TINY, "name": name, **(overrides or {})})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_toml(table) + "\n[sweep]\n" + sweep.strip() + "\n")
    return path


def variant_csvs(out: Path) -> dict[str, bytes]:
    """Every CSV of every variant folder, by relative path."""
    return {
        str(p.relative_to(out)): p.read_bytes() for p in sorted((out / "variants").rglob("*.csv"))
    }


def summary(out: Path) -> pd.DataFrame:
    return pd.read_csv(out / "batch_summary.csv", keep_default_na=False).set_index("variant")


def assert_one_line_error(capsys, code: int, *fragments: str) -> str:
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    for f in fragments:
        assert f in err, f"{f!r} not in {err!r}"
    return err


# --------------------------------------------------------------------------- sweeps


def test_sweep_expands_to_named_cartesian_product(tmp_path):
    path = write_sweep(
        tmp_path / "s.toml",
        """
        seed = [0, 1, 2]
        speed_limits.range_mps = [[10.0, 12.0], [12.5, 14.0]]
        n_runs = [1, 2]
        """,
    )
    variants = expand([path])
    assert len(variants) == 12
    assert all(not v.error for v in variants)
    names = [v.name for v in variants]
    assert names[0] == "seed=0__speed_limits.range_mps=10_12__n_runs=1"
    assert names[-1] == "seed=2__speed_limits.range_mps=12.5_14__n_runs=2"
    assert names == [v.name for v in expand([path])], "names are not deterministic"
    for v in variants:
        assert v.name == v.name.strip() and "/" not in v.name and not v.name.startswith(".")
        sc = v.scenario
        assert sc.seed == v.params["seed"]
        assert list(sc.speed_limits.range_mps) == v.params["speed_limits.range_mps"]
        assert sc.simulation.n_runs == v.params["simulation.n_runs"]  # short key resolved


def test_scenario_without_sweep_is_one_variant_and_several_files_are_prefixed(tmp_path):
    write_sweep(tmp_path / "a.toml", "seed = [1, 2]")
    b = tmp_path / "b.toml"
    b.write_text(dump_toml(scenario_table(TINY)))
    assert [v.name for v in expand([b])] == ["b"]
    names = [v.name for v in expand([str(tmp_path / "*.toml")])]
    assert names == ["a__seed=1", "a__seed=2", "b"]


@pytest.mark.parametrize(
    ("sweep", "fragments"),
    [
        ("colour = [1, 2]", ["unknown sweep key 'colour'"]),
        ("n_vehicle = [5]", ["unknown sweep key 'n_vehicle'", "fleet.n_vehicles"]),
        ("seed = []", ["sweep.seed", "non-empty list"]),
        ("seed = 3", ["sweep.seed", "non-empty list"]),
        ("accel_mps2 = [[1.0, 2.0]]", ["ambiguous", "bounds.accel_mps2", "fleet.accel_mps2"]),
        ("fleet = [1]", ["'fleet' is a table"]),
        ("range_mps = [12.0, 14.0]", ["sweep.range_mps", "pair"]),
        ("seed = [1]\nfleet.seed = [2]", ["unknown sweep key 'fleet.seed'"]),
    ],
)
def test_bad_sweep_is_one_line_error_naming_file_and_key(tmp_path, capsys, sweep, fragments):
    path = write_sweep(tmp_path / "bad.toml", sweep)
    code = main(["batch", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    assert_one_line_error(capsys, code, str(path), *fragments)
    assert not (tmp_path / "out" / "variants").exists()


def test_bad_inputs_are_one_line_errors(tmp_path, capsys):
    code = main(["batch", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")])
    assert_one_line_error(capsys, code, "nope.toml", "not found")
    code = main(["batch", str(tmp_path / "*.toml"), "--out", str(tmp_path / "o")])
    assert_one_line_error(capsys, code, "no scenario file matches")
    path = write_sweep(tmp_path / "s.toml", "seed = [1]")
    code = main(["batch", str(path), "--out", str(tmp_path / "o"), "--workers", "0"])
    assert_one_line_error(capsys, code, "--workers 0")
    code = main(["batch", str(path), "--out", str(tmp_path / "o"), "--address", "x:1"])
    assert_one_line_error(capsys, code, "--address is for --backend ray")


def test_simulate_refuses_a_sweep_file(tmp_path, capsys):
    path = write_sweep(tmp_path / "s.toml", "seed = [1]")
    code = main(["simulate", str(path), "--out", str(tmp_path / "o"), "--quiet"])
    assert_one_line_error(capsys, code, "[sweep]", "macromicro batch")


def test_ray_backend_without_ray_says_how_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # as if not installed
    path = write_sweep(tmp_path / "s.toml", "seed = [1]")
    code = main(["batch", str(path), "--out", str(tmp_path / "o"), "--backend", "ray"])
    assert_one_line_error(capsys, code, "pip install 'macromicro-sumo[ray]'")


# --------------------------------------------------------------------------- faults


def test_failing_variants_leave_failed_rows_and_the_others_complete(tmp_path, capsys):
    """A corrupt net, a corrupt routes file (SUMO's own error) and an infeasible sweep value
    in the middle of the batch: each gets a failed row; every other variant completes."""
    nets = tmp_path / "nets"
    nets.mkdir()
    good = scenario_table()["network"]
    (nets / "bad.net.xml").write_text(Path(good["net_file"]).read_text()[:2000])
    (nets / "bad.add.xml").write_text(Path(good["routes_file"]).read_text()[:300])
    write_sweep(tmp_path / "in" / "a.toml", "seed = [1]")
    write_sweep(
        tmp_path / "in" / "b.toml", "seed = [1]", {"network.net_file": "../nets/bad.net.xml"}
    )
    write_sweep(
        tmp_path / "in" / "c.toml", "seed = [1]", {"network.routes_file": "../nets/bad.add.xml"}
    )
    write_sweep(tmp_path / "in" / "d.toml", "n_vehicles = [5, 10]")  # N = 10 breaks the bounds
    (tmp_path / "in" / "e.toml").write_text("this is [not toml")
    out = tmp_path / "out"
    code = main(["batch", str(tmp_path / "in" / "*.toml"), "--out", str(out), "--workers", "1"])
    assert code == 1
    assert "Traceback" not in capsys.readouterr().err
    s = summary(out)
    assert s.loc["a__seed=1", "status"] == "complete"
    assert s.loc["d__n_vehicles=5", "status"] == "complete"
    failed = {name: s.loc[name, "error"] for name in s.index if s.loc[name, "status"] == "failed"}
    assert set(failed) == {"b__seed=1", "c__seed=1", "d__n_vehicles=10", "e"}
    assert "bad.net.xml" in failed["b__seed=1"]
    assert "[SUMO: Error:" in failed["c__seed=1"]  # SUMO's own message, from its stderr
    assert "bounds.spacing_m" in failed["d__n_vehicles=10"]
    assert "malformed TOML" in failed["e"]
    done = sorted(p.name for p in (out / "variants").iterdir())
    assert done == ["a__seed=1", "d__n_vehicles=5"], "a failed variant left a folder"
    macro = pd.read_csv(out / "batch_macro.csv")
    assert set(macro["variant"]) == {"a__seed=1", "d__n_vehicles=5"}


def _kill_when_running(folder: Path, variant: str, found: list[int], stop: threading.Event):
    """SIGKILL the worker whose stderr goes to ``variant``'s log (it is running it)."""
    mine = str(os.getpid())
    while not stop.is_set():
        for pid in os.listdir("/proc"):
            if not pid.isdigit() or pid == mine:
                continue
            try:
                target = os.readlink(f"/proc/{pid}/fd/2")
            except OSError:
                continue
            if str(folder) in target and f".partial-{variant}." in target:
                os.kill(int(pid), signal.SIGKILL)
                found.append(int(pid))
                return
        time.sleep(0.002)


def test_killed_worker_fails_only_its_variant(tmp_path):
    path = write_sweep(tmp_path / "s.toml", "n_runs = [1, 30]\nseed = [1, 2]")
    out = tmp_path / "out"
    victim = "n_runs=30__seed=1"
    found: list[int] = []
    stop = threading.Event()
    killer = threading.Thread(target=_kill_when_running, args=(out, victim, found, stop))
    killer.start()
    try:
        res = run_batch([path], out, workers=2, progress=False)
    finally:
        stop.set()
        killer.join()
    assert found, "the victim's worker was never seen"
    s = summary(out)
    assert s.loc[victim, "status"] == "failed"
    assert "worker process died" in s.loc[victim, "error"]
    others = s.drop(index=victim)
    assert (others["status"] == "complete").all(), others[["status", "error"]]
    assert res.counts == {"complete": 3, "failed": 1, "reused": 0}
    assert not list((out / "variants").glob(".partial-*"))
    # A re-run redoes only the failed variant.
    res = run_batch([path], out, workers=2, progress=False)
    assert res.counts == {"complete": 4, "reused": 3}


def _wait_for(pred, timeout_s: float = 60.0) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout_s, "timed out"
        time.sleep(0.005)


def _complete(out: Path) -> list[Path]:
    """Manifests of complete variants (pathlib's glob also matches hidden .partial folders)."""
    found = (out / "variants").glob("*/manifest.json")
    return sorted(p for p in found if not p.parent.name.startswith("."))


def _batch_process(path: Path, out: Path, workers: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "macromicro_sumo.cli", "batch", str(path), "--out", str(out)]
    return subprocess.Popen(
        [*cmd, "--workers", str(workers), "--quiet"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a job in a terminal
    )


def test_batch_killed_with_sigkill_and_rerun_redoes_only_the_unfinished(tmp_path):
    # Light variants first, then heavy ones: the kill lands while one is half-done and, with
    # three seeds, before the last has started.
    path = write_sweep(tmp_path / "s.toml", "n_runs = [1, 12]\nseed = [1, 2, 3]")
    ref = tmp_path / "ref"
    assert run_batch([path], ref, workers=2, progress=False).counts["complete"] == 6

    out = tmp_path / "out"
    proc = _batch_process(path, out, workers=1)
    try:
        _wait_for(lambda: _complete(out) and list((out / "variants").glob(".partial-*")))
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and its workers, no clean-up at all
    finally:
        proc.wait()
    before = {p.parent.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in _complete(out)}
    assert 1 <= len(before) < 6
    assert list((out / "variants").glob(".partial-*")), "no half-done variant to redo"

    res = run_batch([path], out, workers=2, progress=False)
    assert res.counts == {"complete": 6, "reused": len(before)}
    after = {p.parent.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in _complete(out)}
    assert {k: after[k] for k in before} == before, "a finished variant was redone"
    s = summary(out)
    assert s["reused"].tolist() == [name in before for name in s.index]
    assert not list((out / "variants").glob(".partial-*"))
    assert variant_csvs(out) == variant_csvs(ref)  # same results, 1 vs 2 workers too
    assert (out / "batch_macro.csv").read_bytes() == (ref / "batch_macro.csv").read_bytes()


def test_ctrl_c_stops_cleanly_and_keeps_finished_variants(tmp_path):
    # A third seed: variants left to start when Ctrl-C lands, however late the poll sees a
    # half-done one (with 4, the last could finish first and the batch exit 0).
    path = write_sweep(tmp_path / "s.toml", "n_runs = [1, 12]\nseed = [1, 2, 3]")
    out = tmp_path / "out"
    proc = _batch_process(path, out, workers=1)
    try:
        _wait_for(lambda: _complete(out) and list((out / "variants").glob(".partial-*")))
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the driver and its workers
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err, err
    assert not list((out / "variants").glob(".partial-*"))
    s = summary(out)
    finished = {p.parent.name for p in _complete(out)}
    assert finished and set(s.index[s["status"] == "complete"]) == finished
    assert set(s["status"]) <= {"complete", "interrupted"} and "interrupted" in set(s["status"])
    assert set(pd.read_csv(out / "batch_macro.csv")["variant"]) == finished


# --------------------------------------------------------------------------- re-runs


def test_rerun_skips_complete_variants_and_redoes_stale_ones(tmp_path):
    path = write_sweep(tmp_path / "s.toml", "seed = [1, 2]")
    out = tmp_path / "out"
    assert run_batch([path], out, workers=1, progress=False).counts["complete"] == 2
    stamp = {p: p.stat().st_mtime_ns for p in _complete(out)}
    assert run_batch([path], out, workers=1, progress=False).counts == {
        "complete": 2,
        "reused": 2,
    }
    assert {p: p.stat().st_mtime_ns for p in _complete(out)} == stamp
    # The base scenario changed: same names, other results, so both are redone.
    write_sweep(path, "seed = [1, 2]", {"simulation.duration_s": 120.0})
    assert run_batch([path], out, workers=1, progress=False).counts == {
        "complete": 2,
        "reused": 0,
    }
    macro = pd.read_csv(out / "batch_macro.csv")
    assert macro["end_s"].max() == 120.0
    assert not list((out / "variants").glob(".trash-*"))


def test_a_stage_that_is_not_installed_fails_its_variants_clearly(tmp_path, monkeypatch):
    monkeypatch.setitem(batch.STAGES, "run", "macromicro_sumo.no_such_pipeline:run")
    path = write_sweep(tmp_path / "s.toml", "seed = [1, 2]")
    res = run_batch([path], tmp_path / "out", stages=("run",), progress=False)
    assert res.counts == {"failed": 2, "reused": 0}
    for error in summary(tmp_path / "out")["error"]:
        assert "stage 'run' is not available" in error
    with pytest.raises(UserError, match="not available"):
        batch.resolve_stage("run")


# --------------------------------------------------------------------------- results


def test_combined_csv_has_one_row_per_variant_run_source_and_interval(tmp_path):
    path = write_sweep(
        tmp_path / "s.toml",
        "seed = [1, 2]\nspeed_limits.range_mps = [[10.0, 12.0], [12.0, 14.0]]",
        {"simulation.n_runs": 2, "simulation.duration_s": 120.0},
    )
    out = tmp_path / "out"
    assert main(["batch", str(path), "--out", str(out), "--workers", "2", "--quiet"]) == 0
    macro = pd.read_csv(out / "batch_macro.csv")
    assert len(macro) == 4 * 2 * 2 * 2  # variants x runs x sources x intervals
    key = ["variant", "run", "source", "begin_s"]
    assert not macro.duplicated(key).any()
    assert set(macro["source"]) == {"detectors", "trajectories"}
    assert macro["seed"].dtype.kind == "i"
    lo, hi = macro["speed_limits.range_mps.lo"], macro["speed_limits.range_mps.hi"]
    assert set(zip(lo, hi, strict=True)) == {(10.0, 12.0), (12.0, 14.0)}
    # The parameter columns repeat the variant's own macro.csv rows unchanged.
    v = "seed=2__speed_limits.range_mps=12_14"
    own = pd.read_csv(out / "variants" / v / "macro.csv")
    mine = macro[macro["variant"] == v].drop(columns=macro.columns[:5]).reset_index(drop=True)
    pd.testing.assert_frame_equal(mine, own)
    s = summary(out)
    assert (s["status"] == "complete").all() and (s["wall_s"].astype(float) > 0).all()
    assert (s["n_runs"] == 2).all() and (s["collisions"] == 0).all()
    det = pd.read_csv(out / "batch_detectors.csv")
    assert not det.duplicated(["variant", "run", "detector_id", "begin_s"]).any()
    assert set(det["variant"]) == set(s.index)
    # SUMO's own detector output is kept per variant.
    assert (out / "variants" / v / "sumo" / "run_000" / "e1.xml").is_file()
    assert (out / "logs" / f"{v}.log").is_file()


def test_ray_backend_gives_the_same_bytes_as_local(tmp_path):
    pytest.importorskip("ray")
    path = write_sweep(tmp_path / "s.toml", "seed = [1, 2]")
    local, ray_out = tmp_path / "local", tmp_path / "ray"
    assert run_batch([path], local, workers=1, progress=False).counts["complete"] == 2
    res = run_batch([path], ray_out, workers=2, backend="ray", progress=False)
    assert res.counts["complete"] == 2
    assert variant_csvs(ray_out) == variant_csvs(local)
    assert (ray_out / "batch_macro.csv").read_bytes() == (local / "batch_macro.csv").read_bytes()


def test_a_node_without_shared_disk_gets_inputs_and_returns_the_same_bytes(tmp_path):
    """What a remote Ray node does: network files arrive as bytes, outputs leave as a tar."""
    nets = tmp_path / "nets"
    nets.mkdir()
    good = scenario_table()["network"]
    for key in ("net_file", "routes_file"):
        (nets / Path(good[key]).name).write_bytes(Path(good[key]).read_bytes())
    path = write_sweep(
        tmp_path / "in" / "s.toml",
        "seed = [1]",
        {
            "network.net_file": f"../nets/{Path(good['net_file']).name}",
            "network.routes_file": f"../nets/{Path(good['routes_file']).name}",
        },
    )
    (v,) = expand([path])
    local = tmp_path / "local"
    assert run_batch([path], local, workers=1, progress=False).counts["complete"] == 1
    inputs = {str(p.resolve()): p.read_bytes() for p in nets.iterdir()}
    moved = tmp_path / "elsewhere"
    nets.rename(moved)  # this "node" does not have the network files
    task = batch.Task(v.name, v.scenario, ("simulate",), str(tmp_path / "unused"), "test")
    outcome, blob = batch.run_shipped(task, inputs)
    assert outcome.ok, outcome.error
    batch._unpack(blob, tmp_path / "back")
    here = {p.name: p.read_bytes() for p in (tmp_path / "back").glob("*.csv")}
    there = {p.name: p.read_bytes() for p in (local / "variants" / v.name).glob("*.csv")}
    assert here == there and len(here) == 7
    assert (tmp_path / "back" / "sumo" / "run_000" / "e1.xml").is_file()

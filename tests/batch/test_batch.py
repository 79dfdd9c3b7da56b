"""``macromicro batch`` against real SUMO: sweeps, failed variants, a killed worker, a killed
batch and its re-run, Ctrl-C, and the same bytes from every backend and worker count; for
ring scenarios and for sections of a user's SUMO network."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from conftest import NETS, ROOT, assert_one_line_error, dump_toml, scenario_table

from macromicro_sumo.batch import backends, tasks
from macromicro_sumo.batch.runner import run_batch
from macromicro_sumo.batch.sweep import expand
from macromicro_sumo.cli import main
from macromicro_sumo.errors import UserError

TINY = {"simulation.n_runs": 1, "simulation.duration_s": 60.0, "detectors.interval_s": 30.0}


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
    """A corrupt net, a corrupt detector file (SUMO's own error) and an infeasible sweep
    value in the middle of the batch: each gets a failed row; every other variant completes."""
    nets = tmp_path / "nets"
    nets.mkdir()
    good = Path(scenario_table()["network"]["net_file"])
    (nets / "bad.net.xml").write_text(good.read_text()[:2000])
    # A ring net whose detector file holds an element only SUMO refuses.
    shutil.copy(good, nets / "c.net.xml")
    dets = (NETS / "ring_r100_e4.det.add.xml").read_text()
    stop = '<busStop id="x" lane="nowhere_0" startPos="0" endPos="10"/>\n</additional>'
    (nets / "c.det.add.xml").write_text(dets.replace("</additional>", stop))
    write_sweep(tmp_path / "in" / "a.toml", "seed = [1]")
    write_sweep(
        tmp_path / "in" / "b.toml", "seed = [1]", {"network.net_file": "../nets/bad.net.xml"}
    )
    write_sweep(tmp_path / "in" / "c.toml", "seed = [1]", {"network.net_file": "../nets/c.net.xml"})
    write_sweep(tmp_path / "in" / "d.toml", "n_vehicles = [5, 130]")  # 130 do not fit
    (tmp_path / "in" / "e.toml").write_text("this is [not toml")
    out = tmp_path / "out"
    code = main(["batch", str(tmp_path / "in" / "*.toml"), "--out", str(out), "--workers", "1"])
    assert code == 1
    assert "Traceback" not in capsys.readouterr().err
    s = summary(out)
    assert s.loc["a__seed=1", "status"] == "complete"
    assert s.loc["d__n_vehicles=5", "status"] == "complete"
    failed = {name: s.loc[name, "error"] for name in s.index if s.loc[name, "status"] == "failed"}
    assert set(failed) == {"b__seed=1", "c__seed=1", "d__n_vehicles=130", "e"}
    assert "bad.net.xml" in failed["b__seed=1"]
    assert "[SUMO: Error:" in failed["c__seed=1"]  # SUMO's own message, from its stderr
    assert "does not fit" in failed["d__n_vehicles=130"]
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


# Slow (25-40 s each): the default run keeps test_failing_variants_leave_failed_rows_... and
# test_rerun_skips_complete_variants_and_redoes_stale_ones for the same rules without a kill.
@pytest.mark.slow
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
        # As a terminal's job gets it: a test run started in the background of a
        # non-interactive shell (CI scripts) inherits SIGINT ignored, and Python keeps it so.
        preexec_fn=_default_sigint,
    )


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
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
    names = sorted(p.name for p in (out / "variants").iterdir())
    assert proc.returncode == 130, f"rc {proc.returncode}, stderr {err!r}, variants {names}"
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


def test_an_unknown_stage_is_a_one_line_error(tmp_path):
    with pytest.raises(UserError, match="unknown stage 'train'; accepted: simulate, run"):
        tasks.resolve_stage("train")
    path = write_sweep(tmp_path / "s.toml", "seed = [1, 2]")
    with pytest.raises(UserError, match="unknown stage 'train'; accepted: simulate, run"):
        run_batch([path], tmp_path / "out", stages=("simulate", "train"), progress=False)
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- results


def test_combined_csv_has_one_row_per_variant_run_source_and_interval(tmp_path):
    path = write_sweep(
        tmp_path / "s.toml",
        "seed = [1, 2]\nspeed_limits.range_mps = [[10.0, 12.0], [12.0, 14.0]]",
        {"simulation.n_runs": 2, "simulation.duration_s": 120.0, "detectors.interval_s": 60.0},
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


@pytest.fixture
def ray_tmp(monkeypatch):
    """Ray's session files (sockets, logs) in a folder of the test's own, removed afterwards:
    by default Ray leaves a session folder in /tmp/ray for every start. Short, under /tmp,
    because Ray's socket paths must fit the 107-byte limit of a Unix socket."""
    pytest.importorskip("ray")
    folder = tempfile.mkdtemp(prefix="mmray", dir="/tmp")
    monkeypatch.setenv("RAY_TMPDIR", folder)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def test_ray_backend_gives_the_same_bytes_as_local(tmp_path, ray_tmp):
    path = write_sweep(tmp_path / "s.toml", "seed = [1, 2]")
    local, ray_out = tmp_path / "local", tmp_path / "ray"
    assert run_batch([path], local, workers=1, progress=False).counts["complete"] == 2
    res = run_batch([path], ray_out, workers=2, backend="ray", progress=False)
    assert res.counts["complete"] == 2
    assert variant_csvs(ray_out) == variant_csvs(local)
    assert (ray_out / "batch_macro.csv").read_bytes() == (local / "batch_macro.csv").read_bytes()
    assert any(Path(ray_tmp).iterdir())  # Ray's session went to the test's folder, not /tmp/ray


def _shipped_csvs(v, inputs: dict, local: Path, tmp_path: Path) -> dict[str, bytes]:
    """Run variant ``v``'s ground truth as a node does (its inputs as bytes ``inputs``), its
    outputs unpacked into ``tmp_path / "back"``: the CSVs, checked equal to the local run's."""
    task = tasks.Task(v.name, v.scenario, ("simulate",), str(tmp_path / "unused"), "test")
    outcome, blob = backends.run_shipped(task, inputs)
    assert outcome.ok, outcome.error
    backends._unpack(blob, tmp_path / "back")
    here = {p.name: p.read_bytes() for p in (tmp_path / "back").glob("*.csv")}
    there = {p.name: p.read_bytes() for p in (local / "variants" / v.name).glob("*.csv")}
    assert here == there
    return here


def test_a_node_without_shared_disk_gets_inputs_and_returns_the_same_bytes(tmp_path):
    """What a remote Ray node does: network files arrive as bytes, outputs leave as a tar."""
    nets = tmp_path / "nets"
    nets.mkdir()
    good = Path(scenario_table()["network"]["net_file"])
    # A ring file reads its net and the ring's detector file beside it.
    for name in (good.name, "ring_r100_e4.det.add.xml"):
        (nets / name).write_bytes((good.parent / name).read_bytes())
    path = write_sweep(
        tmp_path / "in" / "s.toml", "seed = [1]", {"network.net_file": f"../nets/{good.name}"}
    )
    (v,) = expand([path])
    local = tmp_path / "local"
    assert run_batch([path], local, workers=1, progress=False).counts["complete"] == 1
    inputs = backends.shipment(v.scenario)
    assert sorted(Path(k).name for k in inputs) == sorted(p.name for p in nets.iterdir())
    moved = tmp_path / "elsewhere"
    nets.rename(moved)  # this "node" does not have the network files
    here = _shipped_csvs(v, inputs, local, tmp_path)
    assert "trajectories.csv" in here
    assert (tmp_path / "back" / "sumo" / "run_000" / "e1.xml").is_file()


# --------------------------------------------------------------------------- sections

CORRIDOR = ROOT / "scenarios" / "netgen_corridor.toml"
# One 60 s run after a 60 s warm-up, two 30 s intervals: about 0.3 s of SUMO per variant.
SECTION_TINY = {
    "simulation.n_runs": 1,
    "simulation.warmup_s": 60.0,
    "simulation.duration_s": 60.0,
    "detectors.interval_s": 30.0,
    "instrumented.penetration": 0.3,
}
SECTION_FILES = ("macro.csv", "detectors.csv", "trajectories.csv", "k_estimate.csv", "runs.csv")


def section_table(overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The netgen corridor example (its sumocfg by absolute path), ``overrides`` applied."""
    table = tomllib.loads(CORRIDOR.read_text())
    table["network"]["sumocfg"] = str((CORRIDOR.parent / table["network"]["sumocfg"]).resolve())
    for dotted, value in {**SECTION_TINY, **(overrides or {})}.items():
        *parents, leaf = dotted.split(".")
        node = table
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return table


def write_section_sweep(
    path: Path, sweep: str | None, overrides: dict[str, Any] | None = None
) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    text = dump_toml(section_table(overrides))
    path.write_text(text + ("\n[sweep]\n" + sweep.strip() + "\n" if sweep else ""))
    return path


def documented(heading: str) -> list[str]:
    """Column names listed in docs/batch.md under ``heading``."""
    text = (ROOT / "docs" / "batch.md").read_text()
    section = text.split(heading, 1)[1].split("\n### ", 1)[0]
    return re.findall(r"^\| `([^`]+)` \|", section, flags=re.M)


@pytest.fixture(scope="module")
def section_batch(tmp_path_factory) -> tuple[Path, Path]:
    """A section scenario swept over two detector spacings, run with two local workers."""
    folder = tmp_path_factory.mktemp("section")
    path = write_section_sweep(folder / "corridor.toml", "auto_spacing_m = [200.0, 400.0]")
    out = folder / "out"
    assert main(["batch", str(path), "--out", str(out), "--workers", "2", "--quiet"]) == 0
    return path, out


def test_section_sweep_keys_are_the_section_tables(tmp_path):
    path = write_section_sweep(
        tmp_path / "s.toml",
        """
        simulation.n_runs = [1, 2]
        "generator.epochs" = [3]
        instrumented.penetration = [0.2, 0.5]
        auto_spacing_m = [300.0]
        section.edges = [["e0", "e1"], ["e2", "e3", "e4"]]
        """,
    )
    variants = expand([path])
    assert len(variants) == 8 and all(not v.error for v in variants), variants[0].error
    assert variants[0].name == (
        "simulation.n_runs=1__generator.epochs=3__instrumented.penetration=0.2__"
        "auto_spacing_m=300__section.edges=e0_e1"
    )
    for v in variants:
        sc = v.scenario
        assert type(sc).__name__ == "SectionScenario"
        assert sc.simulation.n_runs == v.params["simulation.n_runs"]
        assert sc.generator.epochs == 3
        assert sc.instrumented.penetration == v.params["instrumented.penetration"]
        assert sc.detectors.auto_spacing_m == v.params["detectors.auto_spacing_m"]  # short key
        assert list(sc.section.edges) == v.params["section.edges"]
    # An invalid value fails its own variant, as on the ring.
    path = write_section_sweep(tmp_path / "t.toml", "instrumented.penetration = [0.5, 1.5]")
    bad = {v.name: v.error for v in expand([path])}
    assert not bad["instrumented.penetration=0.5"]
    assert "instrumented.penetration" in bad["instrumented.penetration=1.5"]


@pytest.mark.parametrize(
    ("sweep", "fragments"),
    [
        (
            "colour = [1, 2]",
            [
                "unknown sweep key 'colour' for a section scenario",
                "accepted:",
                "seed",
                "simulation, detectors",
                "detectors.auto_spacing_m",
            ],
        ),
        ("fleet.n_vehicles = [5]", ["unknown sweep key 'fleet.n_vehicles'", "instrumented"]),
        ("auto_spacing = [5.0]", ["unknown sweep key", "detectors.auto_spacing_m"]),
        ("epochs = [1]", ["ambiguous", "generator.epochs", "policy.epochs"]),
        ("detectors = [1]", ["'detectors' is a table", "detectors.interval_s"]),
        ('network.kind = ["ring"]', ["'network.kind' cannot be swept"]),
        ('section.edges = ["e0", "e1"]', ["sweep.section.edges", "must be a list"]),
    ],
)
def test_bad_section_sweep_is_one_line_error_naming_accepted_keys(
    tmp_path, capsys, sweep, fragments
):
    path = write_section_sweep(tmp_path / "bad.toml", sweep)
    code = main(["batch", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    assert_one_line_error(capsys, code, str(path), *fragments)
    assert not (tmp_path / "out" / "variants").exists()


def test_section_batch_runs_every_variant(section_batch):
    path, out = section_batch
    s = summary(out)
    assert list(s.index) == ["auto_spacing_m=200", "auto_spacing_m=400"]
    assert s["detectors.auto_spacing_m"].astype(float).tolist() == [200.0, 400.0]
    assert (s["status"] == "complete").all() and (s["scenario"] == "netgen_corridor").all()
    assert (s["n_runs"].astype(int) == 1).all() and (s["n_intervals"].astype(int) == 2).all()
    assert (s["collisions"].astype(int) == 0).all() and (s["min_gap_m"] == "").all()
    for col in ("traj_mean_speed_mps", "det_mean_speed_mps"):
        assert s[col].astype(float).between(5.0, 40.0).all(), s[col]
    for col in ("traj_density_vehpkm", "det_density_vehpkm", "traj_vehicles", "det_vehicles"):
        assert (s[col].astype(float) > 0).all(), s[col]
    assert (s["k_mean_abs_error_veh"].astype(float) >= 0).all()
    counts = {}
    for name in s.index:
        folder = out / "variants" / name
        for f in (*SECTION_FILES, "manifest.json", "section.json", "variant.json"):
            assert (folder / f).is_file(), folder / f
        assert (folder / "sumo" / "run_000" / "detectors.add.xml").is_file()
        det = pd.read_csv(folder / "detectors.csv")
        assert set(det["source"]) == {"auto"}
        counts[name] = det["detector_id"].nunique()
    # Half the spacing, about twice the loops: the swept value reached the simulation.
    assert counts["auto_spacing_m=200"] > 1.5 * counts["auto_spacing_m=400"]
    macro = pd.read_csv(out / "batch_macro.csv")
    assert not macro.duplicated(["variant", "run", "source", "begin_s"]).any()
    assert len(macro) == 2 * 1 * 2 * 2  # variants x runs x sources x intervals
    v = "auto_spacing_m=400"
    own = pd.read_csv(out / "variants" / v / "macro.csv")
    mine = macro[macro["variant"] == v].drop(columns=macro.columns[:3]).reset_index(drop=True)
    pd.testing.assert_frame_equal(mine, own)
    det = pd.read_csv(out / "batch_detectors.csv")
    assert det.groupby("variant")["detector_id"].nunique().to_dict() == counts
    # The same command again reuses both variants.
    res = run_batch([path], out, workers=2, progress=False)
    assert res.counts == {"complete": 2, "reused": 2}


def test_section_batch_exports_and_documents_its_columns(section_batch):
    _, out = section_batch
    before = {t: (out / f"batch_{t}.csv").read_bytes() for t in ("macro", "detectors", "summary")}
    (out / "batch_macro.csv").unlink()
    assert main(["export", str(out), "--format", "csv"]) == 0
    after = {t: (out / f"batch_{t}.csv").read_bytes() for t in ("macro", "detectors", "summary")}
    assert after == before
    params = {"detectors.auto_spacing_m"}
    for table in ("macro", "detectors"):
        written = list(pd.read_csv(out / f"batch_{table}.csv", nrows=0).columns)
        doc = documented(f"### `batch_{table}`")
        only_e2 = {"sampled_seconds_s"}  # written where the section has E2 detectors
        expect = [c for c in doc if c not in only_e2 or c in written]
        assert doc and [c for c in written if c not in params] == expect
    written = list(pd.read_csv(out / "batch_summary.csv", nrows=0).columns)
    assert [c for c in written if c not in params] == documented("### `batch_summary`")


def test_ring_and_section_files_in_one_batch(tmp_path):
    """A ring file runs the section stage as every section does: one schema for both."""
    write_section_sweep(tmp_path / "in" / "corridor.toml", "seed = [3]")
    write_sweep(tmp_path / "in" / "ring.toml", "seed = [3]")
    out = tmp_path / "out"
    res = run_batch([str(tmp_path / "in" / "*.toml")], out, workers=2, progress=False)
    assert res.counts == {"complete": 2, "reused": 0}
    for v in ("corridor__seed=3", "ring__seed=3"):
        assert (out / "variants" / v / "k_estimate.csv").is_file()
    assert (out / "variants" / "ring__seed=3" / "vehicles.csv").is_file()  # the fleet's draws
    macro = pd.read_csv(out / "batch_macro.csv")
    assert macro["density_vpkm_lane"].notna().all()
    assert set(macro["variant"]) == {"corridor__seed=3", "ring__seed=3"}


def _moved_section(tmp_path: Path) -> tuple[Path, Path]:
    """A section scenario whose sumocfg and additional file live in two other folders."""
    shutil.copytree(NETS / "netgen_corridor", tmp_path / "nets")
    (tmp_path / "extra").mkdir()
    (tmp_path / "extra" / "loops.add.xml").write_text(
        '<additional>\n    <inductionLoop id="u1" lane="e1_0" pos="200" period="30" file="x.xml"/>'
        '\n    <inductionLoop id="u3" lane="e3_0" pos="150" period="30" file="x.xml"/>'
        "\n</additional>\n"
    )
    path = write_section_sweep(
        tmp_path / "in" / "s.toml",
        "seed = [4]",
        {
            "network.sumocfg": "../nets/corridor.sumocfg",
            "network.additional_files": ["../extra/loops.add.xml"],
        },
    )
    return path, tmp_path / "nets"


def test_a_node_without_shared_disk_gets_a_sections_files(tmp_path):
    """The sumocfg, the files it names (relative to it) and the additional file travel as
    bytes, keep their layout on the node, and give the same CSVs as the driver's run."""
    path, nets = _moved_section(tmp_path)
    (v,) = expand([path])
    inputs = backends.shipment(v.scenario)
    names = sorted(Path(k).name for k in inputs)
    assert names == ["corridor.net.xml", "corridor.rou.xml", "corridor.sumocfg", "loops.add.xml"]
    local = tmp_path / "local"
    assert run_batch([path], local, workers=1, progress=False).counts["complete"] == 1
    nets.rename(tmp_path / "gone")
    (tmp_path / "extra").rename(tmp_path / "gone_too")  # this "node" has none of them
    here = _shipped_csvs(v, inputs, local, tmp_path)
    assert set(SECTION_FILES) <= set(here)
    det = pd.read_csv(tmp_path / "back" / "detectors.csv")
    assert set(det["detector_id"]) == {"u1", "u3"}  # the shipped additional file's loops
    # Where the files exist, the scenario is left as it is.
    assert backends._localise(v.scenario, {}, tmp_path) is v.scenario


def test_ray_backend_runs_a_section_sweep_with_the_same_bytes(section_batch, tmp_path, ray_tmp):
    path, local = section_batch
    ray_out = tmp_path / "ray"
    res = run_batch([path], ray_out, workers=2, backend="ray", progress=False)
    assert res.counts == {"complete": 2, "reused": 0}
    assert variant_csvs(ray_out) == variant_csvs(local)
    assert (ray_out / "batch_macro.csv").read_bytes() == (local / "batch_macro.csv").read_bytes()


@pytest.mark.slow  # about 25 s: the generator, three policies and the evaluation
def test_section_run_stage_runs_the_section_pipeline(tmp_path):
    budget = {
        "simulation.n_runs": 2,
        "simulation.duration_s": 120.0,
        "generator.epochs": 4,
        "generator.snapshot_every_s": 10.0,
        "policy.updates": 2,
        "policy.episodes_per_update": 8,
        "evaluation.fcd_episodes": 2,
        "evaluation.lf_trials": 2,
    }
    path = write_section_sweep(tmp_path / "s.toml", "seed = [1]", budget)
    out = tmp_path / "out"
    assert run_batch([path], out, stages=("run",), progress=False).counts["complete"] == 1
    folder = out / "variants" / "seed=1"
    assert (folder / "report.md").is_file()
    assert (folder / "evaluation" / "macro_alignment.csv").is_file()
    s = summary(out)
    assert s.loc["seed=1", "n_runs"] == 2 and s.loc["seed=1", "n_intervals"] == 8
    macro = pd.read_csv(out / "batch_macro.csv")  # found under ground_truth/
    assert len(macro) == 2 * 2 * 4

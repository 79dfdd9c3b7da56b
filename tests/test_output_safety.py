"""What the tool must never do to a user's files: run code from a checkpoint, delete or
replace a folder it did not write, write into the inputs, the home folder or ``/``."""

from __future__ import annotations

import contextlib
import errno
import os
import pickle
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pandas as pd
import pytest
from conftest import SMALL, assert_one_line_error, listing

from macromicro_sumo import cli
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import OUTPUT_MARK, out_lock, prepare_out_dir, staging_dir
from macromicro_sumo.policy.checkpoint import load_checkpoint
from macromicro_sumo.scenario.load import load_scenario


class _RunsCode:
    """A pickle that creates a file when it is loaded: what a crafted policy.pt would do."""

    def __init__(self, witness: Path) -> None:
        self.witness = witness

    def __reduce__(self):
        return (Path.touch, (self.witness,))


def test_a_crafted_policy_checkpoint_runs_no_code(make_scenario, tmp_path):
    witness = tmp_path / "code_ran"
    planted = tmp_path / "policy.pt"
    # torch.save uses pickle underneath; a plain pickle of the payload is what an attacker plants.
    planted.write_bytes(pickle.dumps({"format": "x", "payload": _RunsCode(witness)}, protocol=2))
    import torch

    torch.save({"format": "macromicro-policy", "evil": _RunsCode(witness)}, tmp_path / "p2.pt")
    sc = load_scenario(make_scenario())
    for path in (planted, tmp_path / "p2.pt"):
        with pytest.raises(UserError, match="corrupt or truncated policy checkpoint"):
            load_checkpoint(path, sc)
    assert not witness.exists()


def test_simulate_keeps_a_users_folder_of_the_same_name(make_scenario, tmp_path, capsys):
    out = tmp_path / "out"
    users = out / "sumo"
    users.mkdir(parents=True)
    (users / "my.net.xml").write_text("<net/>\n")
    code = cli.main(["simulate", str(make_scenario(SMALL)), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "was not written by macromicro-sumo" in err
    assert (users / "my.net.xml").read_text() == "<net/>\n"
    assert "manifest.json" not in {p.name for p in out.iterdir()}  # nothing half-moved


def test_simulate_twice_replaces_its_own_folders(make_scenario, tmp_path):
    out = tmp_path / "out"
    path = str(make_scenario(SMALL))
    assert cli.main(["simulate", path, "--out", str(out), "--quiet"]) == 0
    staged = [p for p in out.iterdir() if p.is_dir()]
    assert staged and all((p / OUTPUT_MARK).is_file() for p in staged)
    assert cli.main(["simulate", path, "--out", str(out), "--quiet"]) == 0


def test_staging_refuses_a_file_where_a_folder_goes(tmp_path):
    out = prepare_out_dir(tmp_path / "o")
    (out / "fcd").write_text("user's notes\n")
    with pytest.raises(UserError, match="not this tool's output"), staging_dir(out) as stage:
        (stage / "fcd").mkdir()
        (stage / "a.csv").write_text("x\n")
    assert (out / "fcd").read_text() == "user's notes\n" and not (out / "a.csv").exists()


@pytest.mark.parametrize("where", ["scenario_folder", "scenario_file", "home", "root"])
def test_out_that_holds_an_input_or_is_home_or_root_is_refused(
    make_scenario, tmp_path, capsys, where
):
    scenario = make_scenario()
    out = {
        "scenario_folder": scenario.parent,
        "scenario_file": scenario,
        "home": Path.home(),
        "root": Path("/"),
    }[where]
    before = sorted(p.name for p in scenario.parent.iterdir())
    code = cli.main(["simulate", str(scenario), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: --out") and err.count("\n") == 1, err
    assert sorted(p.name for p in scenario.parent.iterdir()) == before


def test_out_that_holds_the_network_is_refused(make_scenario, tmp_path, capsys):
    from conftest import NETS

    code = cli.main(["simulate", str(make_scenario()), "--out", str(NETS), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "holds the input" in err and "ring_r" in err


@contextlib.contextmanager
def read_only(folder: Path) -> Iterator[None]:
    """``folder`` made unwritable: by its mode, or (as root, who ignores modes) immutable."""
    folder.chmod(0o555)
    immutable = False
    try:
        if os.access(folder, os.W_OK):  # root
            done = subprocess.run(["chattr", "+i", str(folder)], capture_output=True)
            if done.returncode != 0 or not shutil.which("chattr"):
                pytest.skip("cannot make a folder read-only for root here (no chattr +i)")
            immutable = True
        yield
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(folder)], check=True)
        folder.chmod(0o755)


def test_an_existing_read_only_out_is_one_line(make_scenario, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    with read_only(out):
        code = cli.main(["simulate", str(make_scenario()), "--out", str(out), "--quiet"])
        assert_one_line_error(capsys, code, f"{out}: output folder is not writable")
    assert listing(out) == []


def test_a_read_only_out_found_by_the_write_probe(tmp_path, monkeypatch):
    """Whatever makes the folder unwritable (mode, read-only mount), the probe reports it."""

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EROFS, os.strerror(errno.EROFS), str(tmp_path))

    monkeypatch.setattr("tempfile.TemporaryFile", refuse)
    with pytest.raises(UserError, match="not writable .Read-only file system."):
        prepare_out_dir(tmp_path / "o")


@pytest.mark.parametrize("victim", ["trajectories.csv", "macro.csv", "manifest.json"])
def test_disk_full_is_one_line_and_leaves_out_as_it_was(
    make_scenario, tmp_path, capsys, monkeypatch, victim
):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("the user's\n")
    before = listing(out)
    full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    to_csv, write_text = pd.DataFrame.to_csv, Path.write_text

    def csv_full(self, path=None, *args, **kwargs):
        if f".{victim}." in str(path):
            raise full
        return to_csv(self, path, *args, **kwargs)

    def text_full(self, *args, **kwargs):
        if self.name.startswith(f".{victim}."):
            raise full
        return write_text(self, *args, **kwargs)

    monkeypatch.setattr(pd.DataFrame, "to_csv", csv_full)
    monkeypatch.setattr(Path, "write_text", text_full)
    code = cli.main(["simulate", str(make_scenario(SMALL)), "--out", str(out), "--quiet"])
    assert_one_line_error(capsys, code, f"{out / victim}: cannot write (No space left on device)")
    assert listing(out) == before


def test_two_runs_at_once_are_refused_and_a_killed_runs_staging_is_removed(
    make_scenario, tmp_path, capsys
):
    """A second process writing into the same --out is refused while the first stages; the
    staging folder a SIGKILL leaves behind is removed by the next run."""
    out = tmp_path / "out"
    slow = make_scenario({"simulation.n_runs": 40, "simulation.duration_s": 1800.0}, "slow.toml")
    small = str(make_scenario(SMALL))
    first = subprocess.Popen(
        [sys.executable, "-m", "macromicro_sumo.cli", "simulate", str(slow), "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob(".staging-*")):  # staging: it holds the lock from now on
            assert first.poll() is None, first.stderr.read()
            assert time.monotonic() < deadline, "the first run never started staging"
            time.sleep(0.05)
        code = cli.main(["simulate", small, "--out", str(out), "--quiet"])
        assert_one_line_error(
            capsys, code, f"{out}: another macromicro run is writing into this folder"
        )
    finally:
        first.kill()  # SIGKILL: no clean-up of its own runs
        first.wait()
    assert list(out.glob(".staging-*")), "SIGKILL should have left the staging folder"
    assert cli.main(["simulate", small, "--out", str(out), "--quiet"]) == 0
    assert not list(out.glob(".staging-*"))
    assert (out / "manifest.json").is_file()


def test_out_lock_is_reentrant_and_released(tmp_path):
    out = prepare_out_dir(tmp_path / "o")
    with out_lock(out), out_lock(out), staging_dir(out) as stage:
        (stage / "a.csv").write_text("x\n")
    assert (out / "a.csv").is_file()
    with out_lock(out):  # released after the first
        pass


def test_a_second_run_is_refused_while_the_first_trains(make_scenario, tmp_path, capsys):
    """`run` holds its --out for the whole pipeline, not only while a stage stages files:
    a second run into it is refused while the first trains the generator."""
    out = tmp_path / "out"
    slow = make_scenario({**SMALL, "generator.epochs": 100_000}, "slow.toml")
    first = subprocess.Popen(
        [sys.executable, "-m", "macromicro_sumo.cli", "run", str(slow), "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 120
        while not (out / "ground_truth" / "manifest.json").is_file():  # now in Stage I
            assert first.poll() is None, first.stderr.read()
            assert time.monotonic() < deadline, "the first run never finished its ground truth"
            time.sleep(0.05)
        time.sleep(0.5)
        assert first.poll() is None
        before = {p: p.stat().st_mtime_ns for p in (out / "ground_truth").iterdir()}
        code = cli.main(["run", str(slow), "--out", str(out), "--quiet"])
        assert_one_line_error(
            capsys, code, f"{out}: another macromicro run is writing into this folder"
        )
        # refused before it touched anything: the first run's ground truth is as it was
        assert {p: p.stat().st_mtime_ns for p in (out / "ground_truth").iterdir()} == before
    finally:
        first.kill()
        first.wait()

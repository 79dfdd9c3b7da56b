"""Stage II faults: resume after SIGKILL, bad checkpoints, SUMO errors inside an episode."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import write_scenario

from macromicro_sumo import cli
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_envs import make_section_bank
from macromicro_sumo.errors import UserError
from macromicro_sumo.policy.checkpoint import load_checkpoint, load_policy
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs

UPDATES = 12


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    folder = tmp_path_factory.mktemp("faults")
    path = write_scenario(
        folder,
        {
            "simulation.n_runs": 4,
            "simulation.duration_s": 120.0,
            "generator.epochs": 3,
            "policy.updates": UPDATES,
            "policy.checkpoint_every": 2,
            "policy.episodes_per_update": 8,
        },
    )
    gt = folder / "gt"
    assert cli.main(["simulate", str(path), "--out", str(gt), "--quiet"]) == 0
    assert (
        cli.main(
            [
                "train-generator",
                str(path),
                "--data",
                str(gt),
                "--out",
                str(folder / "gen"),
                "--quiet",
            ]
        )
        == 0
    )
    return path, gt, folder / "gen" / "generator.pt"


def _train_args(path, gt, gen, out, *extra):
    return [
        "train-policy",
        str(path),
        "--data",
        str(gt),
        "--generator",
        str(gen),
        "--out",
        str(out),
        "--quiet",
        *extra,
    ]


@pytest.fixture(scope="module")
def trained(setup, tmp_path_factory):
    """One uninterrupted training of ``setup``'s policy (its folder), read by the tests
    below (a test that changes it works on a copy): three trainings fewer."""
    path, gt, gen = setup
    out = tmp_path_factory.mktemp("trained") / "pol"
    assert cli.main(_train_args(path, gt, gen, out)) == 0
    return out


def test_sigkill_then_resume_matches_an_uninterrupted_run(setup, trained, tmp_path):
    path, gt, gen = setup
    ref = trained
    out = tmp_path / "killed"
    ckpt = out / "policy_mix_checkpoint.pt"
    # A SIGKILL leaves the killed process's temporary folders (its env's vTypes file): in
    # this test's own tmp_path, not the machine's /tmp.
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    proc = subprocess.Popen(
        [sys.executable, "-m", "macromicro_sumo.cli", *_train_args(path, gt, gen, out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "TMPDIR": str(scratch)},
    )
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if ckpt.is_file() and torch.load(ckpt, weights_only=True)["update"] >= 4:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "training finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = torch.load(ckpt, weights_only=True)["update"]
    assert done < UPDATES and not (out / "policy.pt").exists()
    assert cli.main(_train_args(path, gt, gen, out, "--resume")) == 0
    log, ref_log = (
        pd.read_csv(out / "policy_train_log.csv"),
        pd.read_csv(ref / "policy_train_log.csv"),
    )
    assert list(log["update"]) == list(range(1, UPDATES + 1))
    # Weights, optimiser and RNG states were restored: the resumed run is the same run.
    cols = ["r_macro", "r_micro_per_pair", "pg_loss", "collisions"]
    pd.testing.assert_frame_equal(log[cols], ref_log[cols], rtol=1e-5)
    a = torch.load(out / "policy.pt", weights_only=True)["state_dict"]
    b = torch.load(ref / "policy.pt", weights_only=True)["state_dict"]
    for k in a:
        torch.testing.assert_close(a[k], b[k])


def test_resume_from_corrupt_checkpoint_is_refused_and_nothing_overwritten(setup, tmp_path, capsys):
    path, gt, gen = setup
    out = tmp_path / "pol"
    out.mkdir()
    ckpt = out / "policy_mix_checkpoint.pt"
    ckpt.write_bytes(b"not a checkpoint")
    assert cli.main(_train_args(path, gt, gen, out, "--resume")) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err.startswith("error:")
        and "corrupt or truncated policy checkpoint" in err
        and "\n" not in err
    )
    assert ckpt.read_bytes() == b"not a checkpoint"
    assert sorted(p.name for p in out.iterdir()) == ["policy_mix_checkpoint.pt"]


def test_resume_from_another_scenario_is_refused(setup, trained, tmp_path, capsys):
    path, gt, gen = setup
    out = tmp_path / "pol"
    shutil.copytree(trained, out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    other = write_scenario(
        tmp_path / "other",
        {"simulation.n_runs": 4, "simulation.duration_s": 120.0, "bounds.accel_mps2": [-2.0, 1.0]},
    )
    assert cli.main(_train_args(other, gt, gen, out, "--resume")) == 2
    err = capsys.readouterr().err
    assert "bounds.accel_mps2" in err and "Traceback" not in err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_sumo_error_inside_an_episode_truncates_with_reason(setup):
    path, gt, gen = setup
    sc, truth, bank = make_section_bank(load_scenario(path), gt, None, "train", 0)
    core = SectionCore(sc, truth.section, bank, scenario_inputs(sc).net_file, seed=0)
    try:
        core.reset(0)
        k = int(core.hidden.sum())
        core.step(np.zeros(k))
        lost = core.ids[int(np.flatnonzero(core.hidden)[0])]
        core.sim.remove_vehicles([lost])  # a hidden vehicle lost mid-episode
        res = core.step(np.zeros(k))
        assert res.truncated and lost in res.error
        # The next episode starts whole again: the lost vehicle is re-inserted.
        core.reset(1)
        res = core.step(np.zeros(int(core.hidden.sum())))
        assert not res.error and not res.truncated
    finally:
        core.close()


def test_a_generator_given_as_policy_is_named_for_what_it_is(setup):
    path, _, gen = setup
    with pytest.raises(
        UserError, match="not a policy checkpoint \\(a 'macromicro-section-generator' file\\)"
    ):
        load_checkpoint(gen, load_scenario(path))


def test_checkpoints_cut_short_after_their_stage_are_refused_by_name(
    setup, trained, tmp_path, capsys
):
    """Generator and policy manifests record their own files: a later stage refuses a
    checkpoint that changed since (issue 19, item 3), before reading a byte of it."""
    path, gt, gen = setup
    pol = tmp_path / "pol"
    shutil.copytree(trained, pol)
    manifest = json.loads((pol / "policy_manifest.json").read_text())
    assert set(manifest["outputs"]) >= {"policy.pt", "policy_train_log.csv"}
    data = (pol / "policy.pt").read_bytes()
    (pol / "policy.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError, match=r"policy\.pt: .*policy_manifest\.json"):
        load_policy(pol / "policy.pt", load_scenario(path))
    gen_copy = tmp_path / "gen"
    shutil.copytree(gen.parent, gen_copy)
    blob = (gen_copy / "generator.pt").read_bytes()
    (gen_copy / "generator.pt").write_bytes(blob[:-10])
    code = cli.main(_train_args(path, gt, gen_copy / "generator.pt", tmp_path / "p2"))
    err = capsys.readouterr().err
    assert (
        code == 2
        and err.count("\n") == 1
        and "generator.pt" in err
        and "generator_manifest.json" in err
    )
    assert not (tmp_path / "p2").exists()

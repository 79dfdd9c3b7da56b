"""Joint refinement (pipeline/refinement.py): Algorithm 1's outer iterations on the small
paper ring (real SUMO, torch), its place in the pipeline's resume rule and in the report."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import SMALL_RING, write_scenario
from test_pipeline import stub_stage, stub_stages
from tiny_pass import tiny_single_pass

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import split_runs
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.pipeline.build import (
    fit_residual_prior,
    refine_stages,
    run_stages,
)
from macromicro_sumo.pipeline.refinement import _episodes, next_step_snapshots, refine
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.report.write import Run, refinement_part
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

pytestmark = pytest.mark.usefixtures("keep_torch_threads")

# The single pass and one refinement in seconds: a few epochs and updates on 4 runs.
TINY = {
    **SMALL_RING,
    "generator.epochs": 3,
    "policy.updates": 2,
    "policy.episodes_per_update": 4,
    "policy.refine_iterations": 1,
    "policy.refine_updates": 2,
    "policy.refine_epochs": 4,
    "policy.refine_lambda_rec": 10.0,
}


@pytest.fixture(scope="module")
def single_pass(small_ring_gt: Path, tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth, generator.pt, policy.pt) of a tiny single pass."""
    sc, gen, pol = tiny_single_pass(tmp_path_factory.mktemp("refine"), small_ring_gt, TINY)
    return sc, small_ring_gt, gen, pol


@pytest.fixture(scope="module")
def refined(single_pass, tmp_path_factory: pytest.TempPathFactory):
    sc, gt, gen, pol = single_pass
    out = tmp_path_factory.mktemp("refined")
    manifest = refine(sc, gt, gen, pol, out, progress=False, fit_prior=fit_residual_prior)
    return out, manifest


def test_next_step_scenes_replay_the_observed_and_move_the_hidden_by_the_policy(single_pass):
    sc, gt, gen, pol = single_pass
    truth = load_section_truth(gt, sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    net, agent = load_section_generator(gen, sc), load_policy(pol, sc)
    ep, snaps = _episodes(sc, truth, net, splits)
    nxt = next_step_snapshots(sc, snaps, ep.bank, ep.make_core, agent, seed=5)
    dt = sc.simulation.step_length_s
    assert 0.8 * len(ep.bank) <= len(nxt) <= len(ep.bank)
    assert (nxt.valid.sum(axis=1) == sc.fleet.n_vehicles).all()  # nobody leaves a ring
    traj = truth.trajectories.set_index(["run", "time_s"]).sort_index()
    starts = zip(ep.bank.run, ep.bank.time_s, strict=True)
    episode = {(r, round(t, 6)): e for e, (r, t) in enumerate(starts)}
    a_min, a_max = sc.bounds.accel_mps2
    for i in range(len(nxt)):
        e = episode[(nxt.run[i], round(nxt.time_s[i] - dt, 6))]
        # Observed: the recorded vehicles at t + dt, to the centimetre.
        rec = traj.loc[(nxt.run[i], nxt.time_s[i]), "arc_m"].to_numpy()
        for a in nxt.arc_m[i][nxt.observed[i]]:
            assert np.abs(rec - a).min() < 1e-2
        # Hidden: the generated vehicles after one policy step, in their slots, within the
        # acceleration bounds of the generated start.
        hid = ep.bank.hidden[e]
        assert np.array_equal(nxt.hidden[i], hid) and nxt.k_true[i] == hid.sum()
        dv = nxt.speed_mps[i][hid] - ep.bank.speed0_mps[e][hid]
        assert ((dv >= a_min * dt - 1e-6) & (dv <= a_max * dt + 1e-6)).all()
        # SUMO's Euler update: the step's distance is its new speed times dt.
        ds = np.mod(nxt.arc_m[i][hid] - ep.bank.arc0_m[e][hid], truth.section.length_m)
        assert (np.abs(ds - nxt.speed_mps[i][hid] * dt) < 1e-3).all()
    assert nxt.k_true.sum() > 0


def test_refinement_pulls_the_generator_to_the_policy_and_writes_loadable_checkpoints(
    single_pass, refined
):
    sc, _, gen, pol = single_pass
    out, manifest = refined
    (row,) = manifest["iterations"]
    # The consistency term falls over the fine-tune's epochs, on the same validation
    # scenes with the same draws.
    assert row["L_rec_after"] < row["L_rec_before"]
    log = pd.read_csv(out / "iter_0" / "generator_train_log.csv")
    assert len(log) == sc.policy.refine_epochs and (log["train_L_rec"] > 0).all()
    # lambda_rec L_rec is part of the loss the fine-tune minimises (and early-stops on).
    assert (log["val_loss"] >= sc.policy.refine_lambda_rec * log["val_L_rec"] - 1e-9).all()
    # weights_only loads of the stages' own formats; both differ from the single pass.
    for refined_net, single_net in (
        (load_section_generator(out / "generator.pt", sc), load_section_generator(gen, sc)),
        (load_policy(out / "policy.pt", sc), load_policy(pol, sc)),
    ):
        a, b = refined_net.state_dict(), single_net.state_dict()
        assert a.keys() == b.keys()
        assert any(not torch.equal(a[k], b[k]) for k in a)
    assert set(json.loads((out / "refine_manifest.json").read_text())["outputs"]) == {
        "generator.pt",
        "policy.pt",
        "refine_log.csv",
    }
    assert len(pd.read_csv(out / "refine_log.csv")) == sc.policy.refine_iterations


def _stub(sc, out: Path, calls: list[str]):
    """The standard and refine stages with stand-ins that only write their manifest."""
    stages, stage = stub_stages(sc, out, calls), stub_stage(sc, calls)
    if sc.policy.refine_iterations > 0:
        stages += refine_stages(
            out,
            lambda gt, gen, pol, ref: stage("refine", ref / "refine_manifest.json"),
            lambda gt, gen, pols, ev: stage("evaluate_refined", ev / "evaluation_manifest.json"),
        )
    return stages


def _redone(sc, out: Path) -> list[str]:
    calls: list[str] = []
    run_stages(sc, _stub(sc, out, calls), out, "", False)
    return calls


def _policy(sc, **values):
    return dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, **values))


def test_refine_keys_are_inputs_of_the_refine_stages_only(make_scenario, tmp_path):
    sc, out = load_scenario(make_scenario()), tmp_path / "run"
    single = _redone(sc, out)
    assert "refine" not in single
    # Switching it on after a finished single pass runs the refinement and its evaluation.
    on = _policy(sc, refine_iterations=1)
    assert _redone(on, out) == ["refine", "evaluate_refined"]
    assert _redone(on, out) == []
    for key in ("refine_updates", "refine_epochs", "refine_lambda_rec"):
        value = getattr(on.policy, key) * 2
        assert _redone(_policy(on, **{key: value}), out) == ["refine", "evaluate_refined"], key
    # A policy key redoes the single pass's policies and the refinement after them.
    redo = _redone(_policy(on, eta=on.policy.eta / 2, refine_epochs=40, refine_updates=40,
                           refine_lambda_rec=2.0), out)  # fmt: skip
    assert redo[-2:] == ["refine", "evaluate_refined"] and "train_policy" in redo
    # Off again: the single pass's stages stay as they are.
    assert _redone(_policy(sc, eta=on.policy.eta / 2), out) == []


def test_report_compares_the_refined_policy_with_the_single_pass(make_scenario, tmp_path):
    sc = _policy(load_scenario(make_scenario()), refine_iterations=2)
    out = tmp_path / "run"
    rows = {"single": (12.0, 0.02), "joint": (12.3, 0.31)}
    for folder, (speed, err) in (("", rows["single"]), ("refined/", rows["joint"])):
        (out / folder / "evaluation").mkdir(parents=True)
        by_k = pd.DataFrame(
            {
                "hidden_count": "estimated",
                "K": [1, 2, 1, 2],
                "method": ["policy", "policy", "ground_truth", "ground_truth"],
                "mean_speed_mps": [speed, speed, 12.0, 12.0],
                "mean_speed_err_mps": [err, err, 0.0, 0.0],
                "collisions": 0,
            }
        )
        # The true-count rows: shown by the estimate's only, as the paper's table.
        by_k = pd.concat([by_k, by_k.assign(hidden_count="true")])
        by_k.to_csv(out / folder / "evaluation" / "macro_alignment_by_k.csv", index=False)
    lines = refinement_part(Run(sc, out, {}))
    assert lines[0] == "## Joint refinement (2 outer iterations) vs single pass"
    table = [line for line in "\n".join(lines).splitlines() if line.startswith("| estimated")]
    assert len(table) == 4  # policy only, both runs, K = 1 and 2
    assert "| true |" not in "\n".join(lines)
    assert "| estimated | 1 | single pass | 12.000 |" in table[0]
    assert "| estimated | 1 | joint refinement | 12.300 |" in table[1]
    assert refinement_part(Run(sc, tmp_path / "none", {})) == []


@pytest.mark.slow
def test_run_with_refinement_writes_the_refined_evaluation_and_the_report(tmp_path):
    over = {
        **TINY,
        "evaluation.fcd_episodes": 1,
        "evaluation.lf_trials": 2,
        "evaluation.lf_duration_s": 20.0,
        "deploy.methods": ["policy"],
    }
    path = write_scenario(tmp_path / "sc", over)
    out = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    assert (out / "refined" / "evaluation" / "macro_alignment_by_k.csv").is_file()
    report = (out / "report.md").read_text()
    assert "## Joint refinement (1 outer iterations) vs single pass" in report
    assert "| joint refinement |" in report and "| single pass |" in report

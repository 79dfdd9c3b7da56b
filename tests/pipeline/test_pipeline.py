"""The whole pipeline end to end on a small ring (a ring file: its closed one-lane section),
and evaluate's bad inputs."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import write_scenario

from macromicro_sumo import cli
from macromicro_sumo.evaluation.section import METHOD_ORDER
from macromicro_sumo.files import write_json, write_manifest
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.pipeline.build import RESUME, run_stages, standard_stages
from macromicro_sumo.scenario.load import load_scenario

# Every stage with the smallest budget that still writes all it writes: 22 s of CPU (was 32,
# with 4 policy updates, 2 FCD episodes, 4 completions a scene, a scene every 5 s and all
# eight methods deployed).
SMALL_RUN = {
    "simulation.n_runs": 4,
    "simulation.duration_s": 120.0,
    "generator.epochs": 4,
    # A scene every 10 s: 11 held-out scenes per K (every K of 1-4) for every method's rollouts.
    "generator.snapshot_every_s": 10.0,
    "policy.updates": 2,
    "policy.episodes_per_update": 8,
    "evaluation.completions_per_scene": 1,
    "evaluation.fcd_episodes": 1,
    "evaluation.lf_trials": 2,
    "evaluation.lf_duration_s": 20.0,
    # Each of the detector-calibrated IDM's evaluations re-runs the training runs: two do
    # (the default 60 made the deploy stage the pipeline's longest).
    "deploy.calibration_evals": 2,
    # Every method is deployed on the random corridor (test_section_pipeline.py); here a
    # learned, a fitted, SUMO's own and the replay (each method's plots cost 1 s).
    "deploy.methods": ["policy", "idm_detectors", "sumo_default", "oracle"],
}


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pipeline")
    path = write_scenario(folder, SMALL_RUN)
    out = folder / "run"
    assert cli.main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    return path, out


def test_run_writes_every_stage_and_the_report(pipeline):
    _, out = pipeline
    for f in (
        "ground_truth/manifest.json",
        "generator/generator.pt",
        "policy/policy.pt",
        "policy/policy_micro_only.pt",
        "policy/policy_macro_only.pt",
        "evaluation/macro_alignment.csv",
        "evaluation/micro_consistency.csv",
        "deploy/deploy_summary.csv",
        "report.md",
        "manifest.json",
    ):
        assert (out / f).is_file(), f
    timings = json.loads((out / "manifest.json").read_text())["timings_s"]
    assert set(timings) >= {"simulate", "train_generator", "train_policy", "evaluate"}
    report = (out / "report.md").read_text()
    assert "## Macro alignment" in report and "| policy |" in report
    assert "paper policy" in report and "Targets for `policy`" in report  # the paper's ring


def test_generator_manifest_gives_the_pairs_slope_per_k(pipeline):
    """The ring's generator summary: the completions' slope of dv on spacing per K beside
    the recorded scenes' own (how the completed scenes' spread moves once driven)."""
    _, out = pipeline
    summary = json.loads((out / "generator" / "generator_manifest.json").read_text())["summary"]
    assert np.isfinite(summary["truth_pair_slope"])
    per_k = [v["pair_slope"] for k, v in summary.items() if k.startswith("generator_K")]
    assert len(per_k) == 4 and all(np.isfinite(per_k))
    assert all(abs(s) < 0.2 for s in [summary["truth_pair_slope"], *per_k])  # [1/s]


def test_generator_manifest_gives_how_the_spread_follows_psi(pipeline):
    """Per K and method the slope of the scenes' spacing std on psi's and the truth's
    (``spread_slope``; None here: the small run holds out two detector intervals)."""
    _, out = pipeline
    summary = json.loads((out / "generator" / "generator_manifest.json").read_text())["summary"]
    per_k = [v for k, v in summary.items() if k.startswith(("generator_K", "uniform_K"))]
    assert len(per_k) == 8
    assert all({"spread_slope", "true_spread_slope"} <= set(v) for v in per_k)


def test_macro_alignment_has_every_method_and_ground_truth_is_the_recording(pipeline):
    _, out = pipeline
    align = pd.read_csv(out / "evaluation" / "macro_alignment_by_k.csv")
    assert {"ground_truth", "policy", "micro_only", "macro_only"} <= set(align["method"])
    assert set(align["method"]) <= set(METHOD_ORDER)
    assert sorted(align["K"].unique()) == [1, 2, 3, 4]
    for col in (
        "mean_speed_mps",
        "std_speed_mps",
        "mean_spacing_m",
        "std_spacing_m",
        "collisions",
        "w1_speed_mps",
        "w1_accel_mps2",
        "w1_spacing_m",
    ):
        assert col in align
    # Mean spacing of a ring is L / N whatever drives the vehicles.
    assert (align["mean_spacing_m"] - 2 * 3.141592653589793 * 100 / 5).abs().max() < 1e-6
    gt = align[align["method"] == "ground_truth"]
    assert (gt["w1_speed_mps"] == 0).all() and (gt["collisions"] == 0).all()
    fcd = list((out / "evaluation" / "fcd").glob("*.fcd.xml"))
    assert fcd and "<fcd-export" in fcd[0].read_text()[:2000]


def test_second_run_skips_finished_stages(pipeline, capsys):
    path, out = pipeline
    before = (out / "policy" / "policy.pt").read_bytes()
    assert cli.main(["run", str(path), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("skipped") >= 6
    assert (out / "policy" / "policy.pt").read_bytes() == before


def _evaluate(path, out, dest, *extra, policy=None):
    """``macromicro evaluate`` on the pipeline's stage outputs (``policy`` replaces its policy)."""
    return cli.main(
        [
            "evaluate",
            str(path),
            "--data",
            str(out / "ground_truth"),
            "--generator",
            str(out / "generator" / "generator.pt"),
            "--policy",
            str(policy or out / "policy" / "policy.pt"),
            "--out",
            str(dest),
            "--quiet",
            *extra,
        ]
    )


def test_evaluate_rejects_policy_of_another_scenario(pipeline, tmp_path, capsys):
    path, out = pipeline
    other = write_scenario(tmp_path / "other", {**SMALL_RUN, "bounds.accel_mps2": [-2.0, 1.0]})
    assert _evaluate(other, out, tmp_path / "ev") == 2
    err = capsys.readouterr().err
    assert "policy was trained for bounds.accel_mps2" in err and len(err.strip().splitlines()) == 1


def test_evaluate_rejects_missing_stage_outputs(pipeline, tmp_path, capsys):
    path, out = pipeline
    assert _evaluate(path, out, tmp_path / "ev", policy=tmp_path / "nope" / "policy.pt") == 2
    assert "checkpoint not found" in capsys.readouterr().err
    assert not (tmp_path / "ev").exists() or not any((tmp_path / "ev").iterdir())


# --------------------------------------------------------------------------- edits between runs

STAGE_MANIFESTS = {
    "simulate": "ground_truth/manifest.json",
    "train_generator": "generator/generator_manifest.json",
    "train_policy": "policy/policy_manifest.json",
    "train_policy_micro_only": "policy/policy_manifest_micro_only.json",
    "train_policy_macro_only": "policy/policy_manifest_macro_only.json",
    "evaluate": "evaluation/evaluation_manifest.json",
}


@pytest.fixture
def finished_copy(pipeline, tmp_path) -> Path:
    """A copy (mtimes kept) of the finished pipeline's folder, for a run of an edited scenario.
    Its policy folder holds the checkpoints of the first run."""
    _, out = pipeline
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    assert (copy / "policy" / "policy_mix_checkpoint.pt").is_file()
    return copy


def _state(out: Path) -> dict[str, tuple[bytes, int]]:
    """Per stage: its manifest's bytes and mtime."""
    return {
        name: ((out / rel).read_bytes(), (out / rel).stat().st_mtime_ns)
        for name, rel in STAGE_MANIFESTS.items()
    }


def _digest(out: Path, stage: str) -> str:
    return json.loads((out / STAGE_MANIFESTS[stage]).read_text())["scenario_sha256"]


@pytest.mark.slow  # the rule itself: test_stages_redo_what_an_edit_reaches (stub stages)
def test_run_after_a_policy_edit_reuses_ground_truth_and_generator(finished_copy, tmp_path):
    """Issue 16: `run` after an edit of policy.eta stopped at the policy's checkpoint of the
    first run ("belongs to another run"), after redoing the ground truth and the generator."""
    out = finished_copy
    before = _state(out)
    files = {
        f: (out / f).stat().st_mtime_ns
        for f in ("ground_truth/trajectories.csv", "generator/generator.pt")
    }
    timings = json.loads((out / "manifest.json").read_text())["timings_s"]
    path = write_scenario(tmp_path / "edited", {**SMALL_RUN, "policy.eta": 0.5})
    assert cli.main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    after, digest = _state(out), load_scenario(path).digest()
    for name in ("simulate", "train_generator", "train_policy_micro_only"):  # micro_only: eta = 0
        assert after[name] == before[name], name
    assert {f: (out / f).stat().st_mtime_ns for f in files} == files
    new_timings = json.loads((out / "manifest.json").read_text())["timings_s"]
    assert {k: new_timings[k] for k in ("simulate", "train_generator")} == {
        k: timings[k] for k in ("simulate", "train_generator")
    }
    for name in ("train_policy", "train_policy_macro_only", "evaluate"):
        assert _digest(out, name) == digest, name
    assert (
        json.loads((out / STAGE_MANIFESTS["train_policy"]).read_text())["scenario"]["policy"]["eta"]
        == 0.5
    )
    assert cli.main(["run", str(path), "--out", str(out), "--quiet"]) == 0  # and now all done
    assert _state(out) == after


@pytest.mark.slow  # the rule itself: test_stages_redo_what_an_edit_reaches (stub stages)
def test_run_after_a_ground_truth_edit_redoes_every_stage(finished_copy, tmp_path):
    out = finished_copy
    before = _state(out)
    path = write_scenario(tmp_path / "edited", {**SMALL_RUN, "simulation.duration_s": 150.0})
    assert cli.main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    after, digest = _state(out), load_scenario(path).digest()
    for name in STAGE_MANIFESTS:
        assert after[name][1] != before[name][1] and _digest(out, name) == digest, name
    traj = pd.read_csv(out / "ground_truth" / "trajectories.csv")
    assert traj["time_s"].max() > 120.0


def stub_stage(sc, calls: list):
    """A stand-in stage that records its name in ``calls`` and writes its manifest for ``sc``."""

    def stage(name: str, manifest: Path) -> None:
        calls.append(name)
        manifest.parent.mkdir(parents=True, exist_ok=True)
        write_json(build_manifest(sc, "", name), manifest)

    return stage


def stub_stages(sc, out: Path, calls: list, truth_reads: tuple[str, ...] = ()):
    """The standard stages with stand-ins (``stub_stage``)."""
    stage = stub_stage(sc, calls)

    def policy(gt, gen, pol, objective, resume) -> None:
        assert resume == RESUME == "auto"
        suffix = "" if objective == "mix" else f"_{objective}"
        stage(f"train_policy{suffix}", pol / f"policy_manifest{suffix}.json")

    return standard_stages(
        out,
        lambda gt: stage("simulate", gt / "manifest.json"),
        lambda gt, gen: stage("train_generator", gen / "generator_manifest.json"),
        policy,
        lambda gt, gen, pols, ev: stage("evaluate", ev / "evaluation_manifest.json"),
        truth_reads,
    )


def _redone(sc, out: Path, truth_reads: tuple[str, ...] = ()) -> list[str]:
    calls: list[str] = []
    run_stages(sc, stub_stages(sc, out, calls, truth_reads), out, "", False)
    return calls


def _edit(sc, table: str, **values):
    return dataclasses.replace(sc, **{table: dataclasses.replace(getattr(sc, table), **values)})


def test_stages_redo_what_an_edit_reaches(make_scenario, tmp_path):
    """The pipeline's skip rule, stage by stage."""
    sc, out = load_scenario(make_scenario()), tmp_path / "run"
    every = list(STAGE_MANIFESTS)
    policies = ["train_policy", "train_policy_micro_only", "train_policy_macro_only"]
    assert _redone(sc, out) == every
    assert _redone(sc, out) == []
    assert _redone(dataclasses.replace(sc, name="renamed"), out) == []
    assert _redone(_edit(sc, "evaluation", lf_trials=3), out) == ["evaluate"]
    sc = _edit(sc, "evaluation", lf_trials=3)
    assert _redone(_edit(sc, "policy", eta=0.7), out) == [
        "train_policy",
        "train_policy_macro_only",
        "evaluate",
    ]
    sc = _edit(sc, "policy", eta=0.7)
    assert _redone(_edit(sc, "policy", objective="micro_only"), out) == []
    assert _redone(_edit(sc, "policy", updates=3), out) == [*policies, "evaluate"]
    sc = _edit(sc, "policy", updates=3)
    assert _redone(_edit(sc, "generator", epochs=2), out) == [
        "train_generator",
        *policies,
        "evaluate",
    ]
    sc = _edit(sc, "generator", epochs=2)
    assert _redone(dataclasses.replace(sc, seed=sc.seed + 1), out) == every
    sc = dataclasses.replace(sc, seed=sc.seed + 1)
    # A stage redone for any reason (here its output gone) redoes the stages that read it.
    (out / STAGE_MANIFESTS["train_generator"]).unlink()
    assert _redone(sc, out) == ["train_generator", *policies, "evaluate"]
    # A section's ground truth reads generator.snapshot_every_s (its K estimates' grid).
    every_s = sc.generator.snapshot_every_s + 1.0
    assert _redone(_edit(sc, "generator", snapshot_every_s=every_s), out)[0] == "train_generator"
    reads = ("generator.snapshot_every_s",)
    assert _redone(_edit(sc, "generator", snapshot_every_s=every_s + 1), out, reads) == every


def test_a_stage_whose_outputs_were_cut_short_is_redone(make_scenario, tmp_path):
    """A ground truth whose CSV no longer matches its manifest's outputs map is redone,
    and with it every stage that reads it."""
    sc, out = load_scenario(make_scenario()), tmp_path / "run"
    assert _redone(sc, out) == list(STAGE_MANIFESTS)
    gt = out / "ground_truth"
    (gt / "trajectories.csv").write_text("run,time_s\n0,0.0\n0,0.5\n")
    write_manifest(build_manifest(sc, "", "simulate"), gt)  # records the file's rows and hash
    assert _redone(sc, out) == []
    (gt / "trajectories.csv").write_text("run,time_s\n0,0.0\n0,0")  # cut mid-row
    assert _redone(sc, out) == list(STAGE_MANIFESTS)

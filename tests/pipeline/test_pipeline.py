"""The whole pipeline end to end on a small ring, and evaluate's bad inputs."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from conftest import write_scenario

from macromicro_sumo import cli
from macromicro_sumo.evaluation.ring import METHOD_ORDER

SMALL_RUN = {
    "simulation.n_runs": 4,
    "simulation.duration_s": 120.0,
    "generator.epochs": 4,
    "policy.updates": 4,
    "policy.episodes_per_update": 8,
    "evaluation.fcd_episodes": 2,
    "evaluation.timespace_s": 20.0,
    "evaluation.lf_trials": 2,
    "evaluation.lf_duration_s": 20.0,
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
        "report.md",
        "manifest.json",
    ):
        assert (out / f).is_file(), f
    timings = json.loads((out / "manifest.json").read_text())["timings_s"]
    assert set(timings) >= {"simulate", "train_generator", "train_policy", "evaluate"}
    report = (out / "report.md").read_text()
    assert "## Macro alignment" in report and "paper policy" in report and "| policy |" in report


def test_macro_alignment_has_every_method_and_ground_truth_is_the_recording(pipeline):
    _, out = pipeline
    align = pd.read_csv(out / "evaluation" / "macro_alignment.csv")
    assert set(align["method"]) == set(METHOD_ORDER)
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
    assert len(fcd) == len(METHOD_ORDER) * 4
    assert "<fcd-export" in fcd[0].read_text()[:2000]


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


@pytest.mark.parametrize("k", ["0", "5", "-1"])
def test_evaluate_rejects_k_outside_the_scenario(pipeline, tmp_path, capsys, k):
    path, out = pipeline
    assert _evaluate(path, out, tmp_path / "ev", "--hidden", k) == 2
    err = capsys.readouterr().err
    assert (
        err.startswith("error: --hidden")
        and "K must be in [1, 4]" in err
        and "Traceback" not in err
    )
    assert not (tmp_path / "ev").exists() or not any((tmp_path / "ev").iterdir())


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


def test_joint_refinement_switch_runs_and_is_compared_in_the_report(tmp_path):
    path = write_scenario(
        tmp_path,
        {
            **SMALL_RUN,
            "policy.refine_iterations": 1,
            "policy.refine_updates": 2,
            "policy.refine_epochs": 2,
        },
    )
    out = tmp_path / "run"
    assert cli.main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    ref = out / "refined"
    assert (ref / "generator.pt").is_file() and (ref / "policy.pt").is_file()
    log = pd.read_csv(ref / "iter_0" / "generator_train_log.csv")
    # The consistency term against the policy's hidden states is part of the loss.
    assert "train_L_rec" in log and (log["train_L_rec"] > 0).all()
    import torch

    a = torch.load(out / "generator" / "generator.pt", weights_only=True)["state_dict"]
    b = torch.load(ref / "generator.pt", weights_only=True)["state_dict"]
    assert any(not torch.equal(a[k], b[k]) for k in a)
    report = (out / "report.md").read_text()
    assert "## Joint refinement (1 outer iterations) vs single pass" in report
    assert "| joint refinement |" in report and "| single pass |" in report


def test_several_completions_per_scene_pair_each_draw_with_the_true_scene(pipeline, tmp_path):
    """One and two completions of every held-out scene: twice the episodes for every method;
    the ground truth is the same scenes repeated (same figures), the generated methods see a
    second, different draw (different spread)."""
    _, out = pipeline
    align = {}
    for m in (1, 2):
        path = write_scenario(
            tmp_path / f"m{m}", {**SMALL_RUN, "evaluation.completions_per_scene": m}
        )
        assert _evaluate(path, out, tmp_path / f"eval{m}") == 0
        csv = tmp_path / f"eval{m}" / "macro_alignment.csv"
        align[m] = pd.read_csv(csv).set_index(["K", "method"])
    once, twice = align[1], align[2]
    assert (twice["episodes"] == 2 * once.loc[twice.index, "episodes"]).all()
    figures = ["mean_speed_mps", "std_speed_mps", "std_spacing_m"]
    pd.testing.assert_frame_equal(
        twice.xs("ground_truth", level="method")[figures],
        once.xs("ground_truth", level="method")[figures],
        rtol=1e-9,
    )
    policy = twice.xs("policy", level="method")["std_spacing_m"]
    assert (policy != once.xs("policy", level="method")["std_spacing_m"]).all()

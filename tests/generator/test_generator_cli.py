"""``macromicro train-generator`` and ``macromicro complete`` end to end through ``main``:
the files they write, and bad input (exit code 2, one ``error:`` line naming the file, no
traceback, nothing written to the output folder)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import write_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.data.ring import load_ground_truth, snapshot_states, split_runs
from macromicro_sumo.files import write_manifest
from macromicro_sumo.generator.ring_model import GeneratorNet
from macromicro_sumo.generator.ring_train import (
    CHECKPOINT_FORMAT,
    load_generator,
    save_generator,
    signature,
)
from macromicro_sumo.scenario.load import load_scenario, scenario_from_dict
from macromicro_sumo.scenario.ring import Scenario

L = 2 * math.pi * 100.0
N = 5
SMALL = {
    "simulation.n_runs": 4,
    "simulation.duration_s": 120.0,
    "generator.epochs": 3,
}
METRIC_COLUMNS = [
    "method",
    "K",
    "n_snapshots",
    "n_feasible_exists",
    "n_no_feasible",
    "feasibility_rate",
    "in_bounds_rate",
    "projected_vehicles",
    "speed_rel_err",
    "spacing_rel_err",
    "spacing_std_m",
    "true_spacing_std_m",
    "L_speed",
    "L_mean",
    "L_min",
    "L_max",
    "L_var",
    "pos_err_m",
    "speed_err_mps",
]
COMPLETION_COLUMNS = [
    "K",
    "snapshot",
    "run",
    "time_s",
    "slot",
    "observed",
    "arc_pos_m",
    "theta_rad",
    "speed_mps",
    "true_arc_pos_m",
    "true_speed_mps",
    "projected_in_snapshot",
]


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


def fails(capsys, argv: list[str], out: Path, *fragments: str) -> str:
    """Run the CLI expecting a user error; the output folder must not change."""
    before, existed = listing(out), out.exists()
    code = main([*argv, "--quiet"])
    captured = capsys.readouterr()
    err = captured.err
    assert code == 2, err
    assert "Traceback" not in err
    assert err.startswith("error: ") and err.endswith("\n") and err.count("\n") == 1, err
    for fragment in fragments:
        assert fragment in err, f"{fragment!r} not in {err!r}"
    assert listing(out) == before, "the output folder changed"
    assert out.exists() == existed, "the output folder was created"
    return err


pytestmark = pytest.mark.usefixtures("keep_torch_threads")


@pytest.fixture(scope="module")
def stage(tmp_path_factory) -> dict:
    """Ground truth (4 runs of 120 s) and a generator trained on it for 3 epochs, via main."""
    folder = tmp_path_factory.mktemp("cli")
    scenario = write_scenario(folder, SMALL)
    gt, gen = folder / "gt", folder / "gen"
    assert main(["simulate", str(scenario), "--out", str(gt), "--quiet"]) == 0
    assert (
        main(["train-generator", str(scenario), "--data", str(gt), "--out", str(gen), "--quiet"])
        == 0
    )
    return {
        "folder": folder,
        "scenario": scenario,
        "sc": load_scenario(scenario),
        "gt": gt,
        "gen": gen,
    }


def held_out_count(sc: Scenario, gt: Path) -> int:
    data = load_ground_truth(gt, sc)
    splits = split_runs(data.runs, sc.generator.held_out_fraction, sc.seed)
    return len(snapshot_states(data, sc, splits["held_out"]))


# --------------------------------------------------------------------------- train-generator


def test_train_generator_writes_a_loadable_checkpoint(stage):
    sc, gen = stage["sc"], stage["gen"]
    files = {p.name for p in gen.iterdir()}
    assert files == {
        "generator.pt",
        "generator_metrics.csv",
        "generator_metrics_per_snapshot.csv",
        "generator_train_log.csv",
        "generator_manifest.json",
    }, files  # no temporary files left behind
    payload = torch.load(gen / "generator.pt", map_location="cpu", weights_only=True)
    assert payload["format"] == CHECKPOINT_FORMAT
    assert payload["signature"] == signature(sc)
    assert payload["signature"]["fleet.n_vehicles"] == N
    assert scenario_from_dict(json.loads(json.dumps(payload["scenario"])), "checkpoint") == sc
    net = load_generator(gen / "generator.pt", sc)
    assert isinstance(net, GeneratorNet) and not net.training
    for name, tensor in net.state_dict().items():
        assert torch.equal(tensor, payload["state_dict"][name]), name


def test_train_generator_metrics_and_log(stage):
    sc, gen = stage["sc"], stage["gen"]
    metrics = pd.read_csv(gen / "generator_metrics.csv")
    assert list(metrics.columns) == METRIC_COLUMNS
    assert sorted(zip(metrics["method"], metrics["K"], strict=True)) == sorted(
        (m, k) for m in ("equal_gap", "generator", "uniform") for k in (1, 2, 3, 4)
    )
    n_held = held_out_count(sc, stage["gt"])
    assert (metrics["n_snapshots"] == n_held).all()
    assert (metrics["n_feasible_exists"] + metrics["n_no_feasible"] == n_held).all()
    assert metrics["feasibility_rate"].between(0, 1).all()
    # Exact look-ahead and projection: the generator's completions always meet the bounds
    # where some completion does; a strict (projection-free) completion is rarer.
    gen_rows = metrics[metrics["method"] == "generator"]
    assert (gen_rows["in_bounds_rate"] == 1.0).all()
    assert (metrics["in_bounds_rate"] >= metrics["feasibility_rate"]).all()
    for col in ("L_speed", "L_mean", "L_min", "L_max", "L_var", "pos_err_m"):
        assert (metrics[col] >= 0).all() and np.isfinite(metrics[col]).all(), col
    per = pd.read_csv(gen / "generator_metrics_per_snapshot.csv")
    assert len(per) == 3 * 4 * n_held
    log = pd.read_csv(gen / "generator_train_log.csv")
    assert list(log["epoch"]) == [0, 1, 2]
    for col in ("train_loss", "val_loss", "train_L_speed", "val_L_var"):
        assert np.isfinite(log[col]).all(), col
    manifest = json.loads((gen / "generator_manifest.json").read_text())
    assert manifest["stage"] == "train-generator" and manifest["epochs"] == 3
    splits = {k: set(v) for k, v in manifest["splits"].items()}
    assert splits["held_out"].isdisjoint(splits["train"] | splits["val"])
    assert splits["train"] | splits["val"] | splits["held_out"] == set(range(4))
    assert manifest["best_val_loss"] == pytest.approx(
        log["val_loss"].min(), abs=2e-6
    )  # CSV keeps 6 decimals


# --------------------------------------------------------------------------- complete


def test_complete_writes_every_held_out_snapshot(stage, capsys, tmp_path):
    sc = stage["sc"]
    out = tmp_path / "comp"
    argv = ["complete", str(stage["scenario"]), "--generator", str(stage["gen"] / "generator.pt")]
    argv += ["--data", str(stage["gt"]), "--out", str(out), "--quiet"]
    assert main(argv) == 0
    assert "completions written to" in capsys.readouterr().out
    comp = pd.read_csv(out / "completions.csv")
    assert list(comp.columns) == COMPLETION_COLUMNS
    n_held = held_out_count(sc, stage["gt"])
    assert len(comp) == 4 * n_held * N
    per_snapshot = comp.groupby(["K", "snapshot"])
    assert len(per_snapshot) == 4 * n_held
    hidden = N - per_snapshot["observed"].sum()
    np.testing.assert_array_equal(hidden.to_numpy(), hidden.index.get_level_values("K"))
    obs = comp[comp["observed"] == 1]
    np.testing.assert_array_equal(obs["arc_pos_m"], obs["true_arc_pos_m"])
    np.testing.assert_array_equal(obs["speed_mps"], obs["true_speed_mps"])
    np.testing.assert_allclose(comp["theta_rad"], 2 * np.pi * comp["arc_pos_m"] / L, atol=2e-6)
    assert comp["arc_pos_m"].between(0, L).all()
    # Held-out runs only, and no two vehicles of a completed snapshot on the same spot.
    held = set(
        json.loads((stage["gen"] / "generator_manifest.json").read_text())["splits"]["held_out"]
    )
    assert set(comp["run"]) == held
    for _, g in per_snapshot:
        s = np.sort(g["arc_pos_m"].to_numpy())
        assert np.diff(np.append(s, s[0] + L)).min() > 1.0
    # Same seed, same bytes.
    again = tmp_path / "again"
    assert main([*argv[:-3], "--out", str(again), "--quiet"]) == 0
    assert (again / "completions.csv").read_bytes() == (out / "completions.csv").read_bytes()


def test_complete_hidden_option_picks_k(stage, tmp_path):
    out = tmp_path / "comp"
    argv = ["complete", str(stage["scenario"]), "--generator", str(stage["gen"] / "generator.pt")]
    argv += ["--data", str(stage["gt"]), "--out", str(out), "--hidden", "0", "5", "--quiet"]
    assert main(argv) == 0
    comp = pd.read_csv(out / "completions.csv")
    assert sorted(comp["K"].unique()) == [0, 5]
    k0 = comp[comp["K"] == 0]
    assert (k0["observed"] == 1).all()
    assert (comp.loc[comp["K"] == 5, "observed"] == 0).all()


# --------------------------------------------------------------------------- bad input


@pytest.fixture
def out(tmp_path: Path) -> Path:
    return tmp_path / "out"


def complete_argv(stage: dict, generator: Path, out: Path, *extra: str, data=None) -> list[str]:
    return [
        "complete",
        str(stage["scenario"]),
        "--generator",
        str(generator),
        "--data",
        str(data or stage["gt"]),
        "--out",
        str(out),
        *extra,
    ]


def other_checkpoint(tmp_path: Path, overrides: dict) -> Path:
    """A real checkpoint saved for another scenario."""
    sc = load_scenario(write_scenario(tmp_path / "other", overrides))
    path = tmp_path / "other.pt"
    save_generator(path, GeneratorNet(8), sc)
    return path


def test_checkpoint_for_another_fleet_size(stage, capsys, tmp_path, out):
    path = other_checkpoint(tmp_path, {"fleet.n_vehicles": 6, "bounds.spacing_m": [90.0, 140.0]})
    fails(
        capsys,
        complete_argv(stage, path, out),
        out,
        str(path),
        "fleet.n_vehicles = 6",
        "has 5",
    )


def test_checkpoint_for_other_bounds(stage, capsys, tmp_path, out):
    path = other_checkpoint(tmp_path, {"bounds.spacing_m": [110.0, 140.0]})
    fails(
        capsys, complete_argv(stage, path, out), out, str(path), "bounds.spacing_m = [110.0, 140.0]"
    )


def test_checkpoint_for_the_other_gap_choice(stage, capsys, tmp_path, out):
    assert stage["sc"].generator.gap_choice == "posterior"  # the paper scenario's
    path = other_checkpoint(tmp_path, {"generator.gap_choice": "network"})
    fails(
        capsys,
        complete_argv(stage, path, out),
        out,
        str(path),
        "generator.gap_choice = network",
        "has posterior",
    )


def test_checkpoint_from_before_the_gap_choice_key_is_a_network_choice(stage, tmp_path, capsys):
    payload = torch.load(stage["gen"] / "generator.pt", map_location="cpu", weights_only=True)
    del payload["signature"]["generator.gap_choice"]
    path = tmp_path / "generator.pt"
    torch.save(payload, path)
    network = write_scenario(tmp_path / "network", {**SMALL, "generator.gap_choice": "network"})
    argv = complete_argv({**stage, "scenario": network}, path, tmp_path / "done", "--hidden", "1")
    assert main([*argv, "--quiet"]) == 0
    assert (tmp_path / "done" / "completions.csv").is_file()
    argv = complete_argv(stage, path, tmp_path / "out")
    fails(capsys, argv, tmp_path / "out", "generator.gap_choice = network", "has posterior")


def test_corrupt_checkpoint(stage, capsys, tmp_path, out):
    path = tmp_path / "generator.pt"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    fails(capsys, complete_argv(stage, path, out), out, str(path), "corrupt or truncated")


def test_truncated_checkpoint(stage, capsys, tmp_path, out):
    whole = (stage["gen"] / "generator.pt").read_bytes()
    path = tmp_path / "generator.pt"
    path.write_bytes(whole[: len(whole) // 2])
    fails(capsys, complete_argv(stage, path, out), out, str(path), "corrupt or truncated")


def test_checkpoint_without_signature(stage, capsys, tmp_path, out):
    payload = torch.load(stage["gen"] / "generator.pt", map_location="cpu", weights_only=True)
    del payload["signature"]
    path = tmp_path / "generator.pt"
    torch.save(payload, path)
    fails(capsys, complete_argv(stage, path, out), out, str(path), "corrupt or truncated")


def test_checkpoint_of_something_else(stage, capsys, tmp_path, out):
    path = tmp_path / "generator.pt"
    torch.save({"weights": torch.zeros(3)}, path)
    fails(capsys, complete_argv(stage, path, out), out, str(path), "not a generator checkpoint")


def test_missing_checkpoint(stage, capsys, tmp_path, out):
    path = tmp_path / "nope.pt"
    fails(capsys, complete_argv(stage, path, out), out, str(path), "not found", "train-generator")


@pytest.mark.parametrize("k", ["7", "-1"])
def test_hidden_count_outside_0_n(stage, capsys, out, k):
    argv = complete_argv(stage, stage["gen"] / "generator.pt", out, "--hidden", "2", k)
    fails(capsys, argv, out, f"--hidden {k}", "K must be in [0, 5]", str(stage["scenario"]))


def copy_gt(stage: dict, tmp_path: Path) -> Path:
    dst = tmp_path / "gt"
    shutil.copytree(stage["gt"], dst, ignore=shutil.ignore_patterns("sumo"))
    return dst


def as_measured(gt: Path) -> None:
    """Re-record the manifest's outputs map after an edit: detectors that really measured
    these values (an edit alone is refused as a corrupt file before psi is checked)."""
    manifest = json.loads((gt / "manifest.json").read_text())
    manifest.pop("outputs", None)
    write_manifest(manifest, gt)


def test_psi_no_completion_can_satisfy(stage, capsys, tmp_path, out):
    gt = copy_gt(stage, tmp_path)
    macro = pd.read_csv(gt / "macro.csv")
    # d_max = 100 m: five gaps of at most 100 m cannot close a 628 m ring.
    macro.loc[macro["source"] == "detectors", "spacing_max_m"] = 100.0
    macro.to_csv(gt / "macro.csv", index=False)
    as_measured(gt)
    argv = complete_argv(stage, stage["gen"] / "generator.pt", out, data=gt)
    fails(capsys, argv, out, str(gt / "macro.csv"), "100.00", "no completion of 5 vehicles")
    train = ["train-generator", str(stage["scenario"]), "--data", str(gt), "--out", str(out)]
    fails(capsys, train, out, str(gt / "macro.csv"), "d_min <= L/N <= d_max")


def test_psi_with_inverted_speed_bounds(stage, capsys, tmp_path, out):
    gt = copy_gt(stage, tmp_path)
    macro = pd.read_csv(gt / "macro.csv")
    macro.loc[macro["source"] == "detectors", "speed_min_mps"] = 20.0
    macro.to_csv(gt / "macro.csv", index=False)
    as_measured(gt)
    out.mkdir()  # an existing output folder stays as it was
    (out / "keep.txt").write_text("keep")
    argv = complete_argv(stage, stage["gen"] / "generator.pt", out, data=gt)
    fails(capsys, argv, out, str(gt / "macro.csv"), "v_min <= v_max")


@pytest.mark.parametrize("missing", ["trajectories.csv", "macro.csv", "manifest.json"])
def test_ground_truth_missing_a_file(stage, capsys, tmp_path, out, missing):
    gt = copy_gt(stage, tmp_path)
    (gt / missing).unlink()
    fails(
        capsys,
        complete_argv(stage, stage["gen"] / "generator.pt", out, data=gt),
        out,
        str(gt),
        f"missing {missing}",
    )
    train = ["train-generator", str(stage["scenario"]), "--data", str(gt), "--out", str(out)]
    fails(capsys, train, out, str(gt), f"missing {missing}")


def test_ground_truth_folder_not_found(stage, capsys, tmp_path, out):
    train = ["train-generator", str(stage["scenario"]), "--data", str(tmp_path / "nope")]
    fails(
        capsys,
        [*train, "--out", str(out)],
        out,
        str(tmp_path / "nope"),
        "run `macromicro simulate`",
    )


def test_ground_truth_of_another_scenario(stage, capsys, tmp_path, out):
    other = write_scenario(
        tmp_path / "six",
        {
            **SMALL,
            "fleet.n_vehicles": 6,
            "bounds.spacing_m": [90.0, 140.0],
        },
    )
    train = ["train-generator", str(other), "--data", str(stage["gt"]), "--out", str(out)]
    fails(capsys, train, out, str(stage["gt"]), "fleet.n_vehicles = 5", "has 6")


def test_output_folder_is_a_file(stage, capsys, tmp_path):
    out = tmp_path / "out.txt"
    out.write_text("keep me")
    train = [
        "train-generator",
        str(stage["scenario"]),
        "--data",
        str(stage["gt"]),
        "--out",
        str(out),
    ]
    assert main([*train, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {out}: output folder is an existing file")
    assert out.read_text() == "keep me"

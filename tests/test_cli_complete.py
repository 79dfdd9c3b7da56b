"""``macromicro complete`` (Stage I alone) and ``evaluate --hidden K`` on the paper ring (its
closed one-lane section) and on an open multi-lane corridor, through the CLI, with real
SUMO ground truths and briefly trained generators; bad input as one line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import SMALL_RING, assert_one_line_error, write_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import split_runs
from macromicro_sumo.env.section_bank import with_future
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.section import held_out_scenes
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

sys.path.insert(0, str(Path(__file__).resolve().parent / "generator"))
from section_checks import lane_is_there  # noqa: E402

pytestmark = pytest.mark.usefixtures("keep_torch_threads")

N = 5  # the paper ring's vehicles
TINY = {
    "generator.epochs": 1,
    "policy.updates": 1,
    "policy.episodes_per_update": 4,
    "evaluation.fcd_episodes": 0,
    "evaluation.lf_trials": 1,
    "evaluation.lf_duration_s": 10.0,
}


@pytest.fixture(scope="module")
def ring(tmp_path_factory, small_ring_gt: Path) -> dict:
    folder = tmp_path_factory.mktemp("complete_ring")
    path = write_scenario(folder, {**SMALL_RING, **TINY})
    gen = folder / "gen"
    args = ["train-generator", str(path), "--data", str(small_ring_gt), "--out", str(gen)]
    assert main([*args, "--quiet"]) == 0
    return {"scenario": path, "gt": small_ring_gt, "gen": gen / "generator.pt", "dir": folder}


def complete(stage: dict, out: Path, *extra: str) -> int:
    argv = ["complete", str(stage["scenario"]), "--generator", str(stage["gen"])]
    return main([*argv, "--data", str(stage["gt"]), "--out", str(out), *extra, "--quiet"])


def truth_at(gt: Path) -> pd.DataFrame:
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str})
    return traj.set_index(["run", "time_s"]).sort_index()


def test_complete_held_out_snapshots_of_the_ring(ring, tmp_path, capsys):
    out = tmp_path / "comp"
    assert complete(ring, out) == 0
    assert "completions.csv" in capsys.readouterr().out
    comp = pd.read_csv(out / "completions.csv")
    hidden = pd.read_csv(out / "hidden_truth.csv")
    manifest = json.loads((out / "complete_manifest.json").read_text())
    # Every K of generator.hidden_eval, each scene of a held-out run, K vehicles generated.
    assert manifest["hidden_counts"] == [1, 2, 3, 4]
    assert set(comp["k_generated"]) == {1, 2, 3, 4}
    sc = load_scenario(ring["scenario"])
    held = split_runs(np.arange(4), sc.generator.held_out_fraction, sc.seed)["held_out"]
    assert set(comp["run"]) == set(held.tolist())
    per = comp.groupby("scene")
    np.testing.assert_array_equal(
        per["role"].apply(lambda r: (r == "generated").sum()), per["k_generated"].first()
    )
    assert (per.size() == N).all()
    # Observed + hidden truth rows are the recorded scene; observed ones are copied exactly.
    truth = truth_at(ring["gt"])
    obs = comp[comp["role"] == "observed"]
    for (run, t), g in obs.groupby(["run", "time_s"]):
        scene = truth.loc[(run, t)]
        assert np.isin(g["arc_m"].round(4), scene["arc_m"].round(4)).all()
    assert len(obs) + len(hidden) == len(comp)
    # On the loop: arcs in [0, L), no two vehicles of a scene closer than a car length.
    length = Section.read(ring["gt"] / "section.json").length_m
    assert comp["arc_m"].between(0, length).all()
    for _, g in per:
        s = np.sort(g["arc_m"].to_numpy())
        assert np.diff(np.append(s, s[0] + length)).min() > 4.0
    metrics = pd.read_csv(out / "completion_metrics.csv")
    assert len(metrics) == per.ngroups and (metrics["violations"] == 0).all()
    # Same seed, same bytes.
    assert complete(ring, tmp_path / "again") == 0
    again = (tmp_path / "again" / "completions.csv").read_bytes()
    assert again == (out / "completions.csv").read_bytes()


def test_several_seeded_completions_and_hidden_zero_and_all(ring, tmp_path):
    out = tmp_path / "comp"
    assert complete(ring, out, "--hidden", "0", "5", "--completions", "3", "--seed", "11") == 0
    comp = pd.read_csv(out / "completions.csv")
    assert sorted(comp["completion"].unique()) == [0, 1, 2]
    assert (comp.loc[comp["k_generated"] == 0, "role"] == "observed").all()
    assert (comp.loc[comp["k_generated"] == 5, "role"] == "generated").all()
    gen = comp[comp["role"] == "generated"]
    first, second = (gen[gen["completion"] == c]["arc_m"].to_numpy() for c in (0, 1))
    assert len(first) == len(second) and not np.allclose(first, second)
    # completion c is seeded seed + c: the first of --seed 12 is the second of --seed 11
    assert complete(ring, tmp_path / "s12", "--hidden", "0", "5", "--seed", "12") == 0
    s12 = pd.read_csv(tmp_path / "s12" / "completions.csv")
    np.testing.assert_array_equal(s12["arc_m"], comp[comp["completion"] == 1]["arc_m"].to_numpy())


def test_complete_a_users_csv_of_observed_vehicles(ring, tmp_path):
    truth = truth_at(ring["gt"]).reset_index()
    scene = truth[(truth["run"] == 1) & np.isclose(truth["time_s"], 60.0)]
    seen = scene.iloc[:3][["run", "time_s", "lane_index", "arc_m", "speed_mps"]]
    seen.to_csv(tmp_path / "seen.csv", index=False)
    assert complete(ring, tmp_path / "a", "--snapshot", str(tmp_path / "seen.csv")) == 0
    comp = pd.read_csv(tmp_path / "a" / "completions.csv")
    # The ring's detectors count all 5: the 2 the user did not list are generated.
    assert (comp["k_generated"] == N - 3).all() and (comp["k_true"] == -1).all()
    assert (comp["role"] == "generated").sum() == N - 3
    np.testing.assert_allclose(
        np.sort(comp.loc[comp["role"] == "observed", "arc_m"]), np.sort(seen["arc_m"]), atol=1e-6
    )
    assert not (tmp_path / "a" / "hidden_truth.csv").exists()  # nobody knows the truth
    # The same vehicles by SUMO lane position (edge_id, pos_m): the same completion.
    section = Section.read(ring["gt"] / "section.json")
    edge = section.edge_index(seen["arc_m"].to_numpy())
    by_lane = seen.drop(columns="arc_m").assign(
        edge_id=[section.edge_ids[e] for e in edge],
        pos_m=seen["arc_m"].to_numpy() - section.offsets_m[edge],
    )
    by_lane.to_csv(tmp_path / "lanes.csv", index=False)
    assert complete(ring, tmp_path / "b", "--snapshot", str(tmp_path / "lanes.csv")) == 0
    other = pd.read_csv(tmp_path / "b" / "completions.csv")
    np.testing.assert_allclose(other["arc_m"], comp["arc_m"], atol=1e-4)
    # One recorded snapshot by RUN:TIME, hiding 2 of its 5.
    assert complete(ring, tmp_path / "c", "--snapshot", "1:60", "--hidden", "2") == 0
    one = pd.read_csv(tmp_path / "c" / "completions.csv")
    assert set(one["time_s"]) == {60.0} and (one["role"] == "generated").sum() == 2
    assert len(pd.read_csv(tmp_path / "c" / "hidden_truth.csv")) == 2


@pytest.mark.parametrize(
    "rows, extra, fragments",
    [
        ("run,time_s,lane_index,speed_mps\n1,60,0,11\n", (), ["missing column(s) arc_m"]),
        ("run,time_s,lane_index,arc_m,speed_mps\n1,60,1,10,11\n", (), ["lane_index", "[0, 0]"]),
        ("run,time_s,lane_index,arc_m,speed_mps\n1,60,0,900,11\n", (), ["arc_m", "line 2"]),
        ("run,time_s,lane_index,arc_m,speed_mps\n1,60,0,10,x\n", (), ["speed_mps", "finite"]),
        ("run,time_s,lane_index,arc_m,speed_mps\n7,60,0,10,11\n", (), ["run 7", "accepted"]),
        ("run,time_s,lane_index,arc_m,speed_mps\n1,62.5,0,10,11\n", (), ["--hidden K"]),
        (None, ("--hidden", "6"), ["--hidden 6", "[0, 5]"]),
        (None, ("--completions", "0"), ["--completions 0", "1..100"]),
        (None, ("--snapshot", "9:60"), ["no run 9", "accepted runs"]),
        (None, ("--snapshot", "1:61"), ["t = 61 s", "snapshot_every_s"]),
    ],
)
def test_bad_input_is_one_line(ring, tmp_path, capsys, rows, extra, fragments):
    if rows is not None:
        (tmp_path / "seen.csv").write_text(rows)
        extra = ("--snapshot", str(tmp_path / "seen.csv"), *extra)
    code = complete(ring, tmp_path / "out", *extra)
    assert_one_line_error(capsys, code, *fragments)
    assert not (tmp_path / "out").exists()


def test_evaluate_only_the_scenes_hiding_k(ring, tmp_path, capsys):
    pol = tmp_path / "pol"
    args = ["train-policy", str(ring["scenario"]), "--data", str(ring["gt"])]
    assert main([*args, "--generator", str(ring["gen"]), "--out", str(pol), "--quiet"]) == 0
    ev = ["evaluate", str(ring["scenario"]), "--data", str(ring["gt"]), "--generator"]
    ev += [str(ring["gen"]), "--policy", str(pol / "policy.pt")]
    assert main([*ev, "--out", str(tmp_path / "ev"), "--hidden", "2", "--quiet"]) == 0
    by_k = pd.read_csv(tmp_path / "ev" / "macro_alignment_by_k.csv")
    assert set(by_k["K"]) == {2} and (by_k["collisions"] >= 0).all()
    manifest = json.loads((tmp_path / "ev" / "evaluation_manifest.json").read_text())
    assert manifest["hidden_counts"] == [2] and list(manifest["episodes_by_k"]) == ["2"]
    assert manifest["episodes"] == manifest["episodes_by_k"]["2"] > 0
    capsys.readouterr()
    code = main([*ev, "--out", str(tmp_path / "bad"), "--hidden", "0", "--quiet"])
    assert_one_line_error(capsys, code, "--hidden 0", "[1, 5]")
    assert not (tmp_path / "bad").exists()


# ------------------------------------------------------------------ an open multi-lane section


def test_complete_on_an_open_multilane_section(netgen_corridor, tmp_path, capsys):
    corridor = netgen_corridor
    assert complete(corridor, tmp_path / "all") == 0
    comp = pd.read_csv(tmp_path / "all" / "completions.csv")
    hidden = pd.read_csv(tmp_path / "all" / "hidden_truth.csv")
    section = Section.read(corridor["gt"] / "section.json")
    # The instrumented vehicles are the observed ones; the generator places the detectors'
    # estimate (k_source), each on a lane that exists where it stands.
    obs = comp[comp["role"] == "observed"]
    truth = truth_at(corridor["gt"])
    for (run, t), g in obs.groupby(["run", "time_s"]):
        assert len(g) == int(truth.loc[(run, t), "observed"].sum())
    gen = comp[comp["role"] == "generated"]
    per = gen.groupby("scene").size()
    np.testing.assert_array_equal(per, comp.groupby("scene")["k_generated"].first()[per.index])
    # In a junction a lane index is the lane it leads to (SUMO's internal lanes say which).
    where = zip(gen["lane_index"], gen["arc_m"], strict=True)
    assert all(lane_is_there(section, int(lane), float(arc)) for lane, arc in where)
    k_true = comp.groupby("scene")["k_true"].first()
    hid = hidden.groupby("scene").size().reindex(k_true.index, fill_value=0)
    np.testing.assert_array_equal(hid, k_true)
    # --hidden K keeps the scenes that hide K (the simulation's count).
    k = int(comp["k_true"].mode()[0])
    assert complete(corridor, tmp_path / "k", "--hidden", str(k)) == 0
    only = pd.read_csv(tmp_path / "k" / "completions.csv")
    assert set(only["k_true"]) == {k}
    assert only["scene"].nunique() == (comp.groupby("scene")["k_true"].first() == k).sum()
    capsys.readouterr()
    code = complete(corridor, tmp_path / "bad", "--hidden", "999")
    assert_one_line_error(capsys, code, "--hidden 999", "counted by the simulation", "accepted")


def test_evaluation_scenes_hiding_k_on_a_section(netgen_corridor):
    """evaluate --hidden on a section keeps the held-out scenes whose simulated hidden count
    is K and that have a recorded future, as one K's episodes (the per-K table's)."""
    corridor = netgen_corridor
    sc = load_scenario(corridor["scenario"])
    truth = load_section_truth(corridor["gt"], sc)
    held = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["held_out"]
    h = sc.evaluation.horizon_steps
    every, _ = held_out_scenes(sc, truth, held, h)
    k = int(np.bincount(every.k_true).argmax())
    scenes, by_k = held_out_scenes(sc, truth, held, h, [k])
    assert set(scenes.k_true.tolist()) == {k} and by_k == {k: range(0, len(scenes))}
    kept = every.take(with_future(truth, every, h, sc.simulation.step_length_s))
    assert len(scenes) == int((kept.k_true == k).sum()) > 0
    with pytest.raises(UserError, match=r"--hidden 0: .*accepted: \d"):
        held_out_scenes(sc, truth, held, h, [0])

"""``idm_true`` on a section (``evaluation.idm_true``): each hidden vehicle driven by its own
ground-truth IDM parameters where the truth records them (a fleet's vehicles.csv), left out
with the reason elsewhere. A small fleet on the ring network as a closed one-lane section,
every vehicle recorded, K random ones hidden per snapshot; real SUMO runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fleet_scenarios import small_fleet_table, write_fleet_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import (
    SectionSnapshots,
    concat_snapshots,
    recorded_snapshots,
    snapshots_by_k,
    split_runs,
)
from macromicro_sumo.env.section_bank import build_section_bank
from macromicro_sumo.env.section_observations import initial_observations
from macromicro_sumo.evaluation.idm_fit import IdmParams, idm_policy_accel
from macromicro_sumo.evaluation.idm_true import PARAMS, true_idm_by_episode, true_idm_table
from macromicro_sumo.evaluation.section import TRUE_REUSED
from macromicro_sumo.report.write import SECTION_REPORT, Run
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

N = 4
HORIZON = 4


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(scenario, folder) with the stages up to the evaluation, tiny budgets."""
    tmp = tmp_path_factory.mktemp("section_idm_true")
    path = write_fleet_scenario(tmp, small_fleet_table(N))
    gt, gen, pol, ev = (tmp / d for d in ("ground_truth", "generator", "policy", "evaluation"))
    q = ["--quiet"]
    assert main(["simulate", str(path), "--out", str(gt), *q]) == 0
    assert main(["train-generator", str(path), "--data", str(gt), "--out", str(gen), *q]) == 0
    args = ["--data", str(gt), "--generator", str(gen / "generator.pt")]
    assert main(["train-policy", str(path), *args, "--out", str(pol), *q]) == 0
    policy = ["--policy", str(pol / "policy.pt")]
    assert main(["evaluate", str(path), *args, *policy, "--out", str(ev), *q]) == 0
    return path, tmp


def held_out_scenes(sc, truth) -> SectionSnapshots:
    """Every held-out snapshot with a recorded future at K = 1..3, as the evaluation's."""
    held = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["held_out"]
    by_k = snapshots_by_k(recorded_snapshots(truth, sc, held), range(1, N), sc.seed)
    snaps = concat_snapshots(list(by_k.values()))
    last = truth.trajectories["time_s"].max()
    return snaps.take(np.flatnonzero(snaps.time_s + HORIZON * 0.5 <= last + 1e-6))


def as_generated(shift_m: float = 0.0, extra_m: float | None = None):
    """A completion whose generated vehicles are the true hidden ones, arcs moved by
    ``shift_m`` and slots reversed (a slot is not a vehicle); with ``extra_m``, one more
    generated vehicle that far ahead of the first generated one."""

    def fn(s: SectionSnapshots):
        lane, arc, speed = s.lane[:, ::-1], s.arc_m[:, ::-1], s.speed_mps[:, ::-1]
        valid, gen = s.valid[:, ::-1], (s.valid & ~s.observed)[:, ::-1]
        arc = np.where(gen, arc + shift_m, arc)
        if extra_m is not None:
            first = np.take_along_axis(arc, np.argmax(gen, axis=1)[:, None], axis=1)
            lane = np.hstack([lane, np.zeros((len(s), 1), dtype=lane.dtype)])
            arc = np.hstack([arc, first + extra_m])
            speed = np.hstack([speed, np.full((len(s), 1), 10.0)])
            valid = np.hstack([valid, np.ones((len(s), 1), dtype=bool)])
            gen = np.hstack([gen, np.ones((len(s), 1), dtype=bool)])
        return lane, arc, speed, valid, gen

    return fn


def params_at(truth, bank, e: int) -> pd.DataFrame:
    """The recorded vehicles at episode ``e``'s generated positions, with their parameters
    from vehicles.csv (found by arc in the trajectories, independently of the module)."""
    traj = truth.trajectories
    scene = traj[(traj["run"] == bank.run[e]) & np.isclose(traj["time_s"], bank.time_s[e])]
    veh = pd.read_csv(truth.folder / "vehicles.csv", dtype={"vehicle_id": str})
    veh = veh[veh["run"] == bank.run[e]].set_index("vehicle_id")
    length = truth.section.length_m
    rows = []
    for arc in bank.arc0_m[e, bank.hidden[e]]:
        d = np.abs(np.mod(scene["arc_m"].to_numpy() - arc + length / 2, length) - length / 2)
        rows.append(veh.loc[scene["vehicle_id"].iloc[int(np.argmin(d))]])
    return pd.DataFrame(rows)


def test_each_generated_vehicle_gets_the_parameters_of_the_vehicle_it_stands_for(fleet) -> None:
    path, tmp = fleet
    sc = load_scenario(path)
    truth = load_section_truth(tmp / "ground_truth", sc)
    table, note = true_idm_table(truth)
    assert table is not None and "vehicles.csv" in note
    snaps = held_out_scenes(sc, truth)
    for shift in (0.0, 1.5):
        bank = build_section_bank(sc, truth, snaps, as_generated(shift), horizon=HORIZON)
        params = true_idm_by_episode(truth, table, snaps, bank)
        assert len(params) == len(bank)
        for e in range(0, len(bank), 5):
            want = params_at(truth, bank, e)
            for field in PARAMS[:-1]:
                assert np.array_equal(getattr(params[e], field), want[field].to_numpy()), field
    # The fleet's parameters differ per vehicle, so a wrong match would show above.
    assert table.groupby("run")["tau_s"].nunique().min() == N


def test_an_extra_generated_vehicle_takes_its_nearest_hidden_vehicles(fleet) -> None:
    path, tmp = fleet
    sc = load_scenario(path)
    truth = load_section_truth(tmp / "ground_truth", sc)
    table, _ = true_idm_table(truth)
    snaps = held_out_scenes(sc, truth)
    bank = build_section_bank(sc, truth, snaps, as_generated(extra_m=0.5), horizon=HORIZON)
    params = true_idm_by_episode(truth, table, snaps, bank)
    for e in range(0, len(bank), 5):
        k = int(snaps.hidden[e].sum())
        tau = params[e].tau_s  # in slot order: the first generated first, the extra last
        assert len(tau) == k + 1 and len(set(tau[:-1])) == k  # the others: one each
        assert tau[-1] == tau[0]


def test_the_true_parameters_predict_the_recorded_actions(fleet) -> None:
    """Physics: on the true scenes each hidden vehicle's own IDM gives its recorded
    acceleration (the truth is SUMO's IDM with one Euler step per step), another vehicle's
    does not. Where a lower limit lies ahead SUMO's drivers brake before it and textbook
    IDM does not (docs/experiments.md): those states are left out."""
    path, tmp = fleet
    sc = load_scenario(path)
    truth = load_section_truth(tmp / "ground_truth", sc)
    table, _ = true_idm_table(truth)
    snaps = held_out_scenes(sc, truth)
    bank = build_section_bank(sc, truth, snaps, as_generated(), horizon=HORIZON)
    params = true_idm_by_episode(truth, table, snaps, bank)
    obs = initial_observations(sc, truth.section, bank)  # lookahead: [4] the next limit
    start = np.concatenate([[0], np.cumsum(bank.valid.sum(axis=1))])
    traj = truth.trajectories.set_index(["run", "time_s", "vehicle_id"])["speed_mps"]
    own, rotated = [], []
    for e in range(len(bank)):
        o = obs[start[e] : start[e + 1]][bank.hidden[e][bank.valid[e]]]
        ids = params_at(truth, bank, e).index
        v1 = np.array([traj[(bank.run[e], bank.time_s[e] + 0.5, v)] for v in ids])
        err = idm_policy_accel(o, params[e], 5.0) - (v1 - o[:, 0]) / 0.5
        p = params[e]
        roll = IdmParams(*(np.roll(getattr(p, f), 1) for f in PARAMS[:-1]), p.delta)
        err_rolled = idm_policy_accel(o, roll, 5.0) - (v1 - o[:, 0]) / 0.5
        no_lower_ahead = o[:, 4] >= o[:, 1]
        own.append(err[no_lower_ahead])
        if len(ids) > 1:
            rotated.append(err_rolled[no_lower_ahead])
    own_err, rotated_err = np.abs(np.concatenate(own)), np.abs(np.concatenate(rotated))
    assert len(own_err) >= 20
    assert np.median(own_err) < 1e-4 and own_err.max() < 0.02, np.sort(own_err)[-5:]
    assert np.median(rotated_err) > 0.02, np.median(rotated_err)


def test_the_evaluation_and_report_show_idm_true(fleet) -> None:
    path, tmp = fleet
    align = pd.read_csv(tmp / "evaluation" / "macro_alignment.csv")
    oracle = align[align["method"] == "idm_true"]
    assert sorted(oracle["hidden_count"]) == ["estimated", "true"]
    assert (oracle["episodes"] == align[align["method"] == "policy"]["episodes"].to_numpy()).all()
    by_k = pd.read_csv(tmp / "evaluation" / "macro_alignment_by_k.csv")
    assert sorted(by_k[by_k["method"] == "idm_true"]["K"].unique()) == [1, 2, 3]
    manifest = json.loads((tmp / "evaluation" / "evaluation_manifest.json").read_text())
    assert manifest["idm_true"].startswith("idm_true: each hidden vehicle's own IDM")
    # report.md's parts, as write_report joins them (the plots left out: slow, not at issue)
    r = Run(load_scenario(path), tmp, {})
    report = "\n".join(line for part in SECTION_REPORT.parts for line in part(r))
    assert "- `idm_true` (oracle): each hidden vehicle's own IDM parameters" in report
    assert "| idm_true |" in report and "idm_true: each hidden vehicle's own IDM" in report


def test_one_pass_stands_for_both_hidden_counts_where_they_agree(fleet) -> None:
    """The ring's detectors count every vehicle: each scene's estimated K is its true K, so
    the true count's rows are the estimated pass's, relabelled (one pass instead of two
    that differ only in the seed), in every table, and the manifest says so."""
    path, tmp = fleet
    sc = load_scenario(path)
    truth = load_section_truth(tmp / "ground_truth", sc)
    snaps = held_out_scenes(sc, truth)
    assert np.array_equal(snaps.k_est, snaps.k_true)
    ev = tmp / "evaluation"
    manifest = json.loads((ev / "evaluation_manifest.json").read_text())
    assert manifest["true_count_rows"] == TRUE_REUSED
    for name in ("macro_alignment.csv", "macro_alignment_by_k.csv", "safety.csv"):
        table = pd.read_csv(ev / name)
        est, true = (
            table[table["hidden_count"] == c].drop(columns="hidden_count").reset_index(drop=True)
            for c in ("estimated", "true")
        )
        assert len(est) >= 4 and len(true) == len(est), name
        pd.testing.assert_frame_equal(est, true)
    samples = pd.read_csv(ev / "eval_samples.csv")
    counts = samples["hidden_count"].value_counts()
    assert counts["estimated"] == counts["true"] > 0


def test_idm_true_is_left_out_where_the_truth_has_no_parameters(field_truth: Path) -> None:
    truth = load_section_truth(field_truth)
    table, note = true_idm_table(truth)
    assert table is None
    assert note.startswith("idm_true (oracle) left out:") and "\n" not in note
    for model in set(truth.vtypes["car_follow_model"].astype(str)):
        assert model in note


def test_the_evaluation_rolls_out_with_the_scenarios_safety_layer(fleet) -> None:
    """``policy.safety`` holds in evaluation rollouts as in training: with "none" every
    method's commands apply exactly (nothing capped, no policy-alone rerun), and safety.csv
    and the manifest say so; the default ("sumo") evaluation beside it, on the same stages."""
    path, tmp = fleet
    table = small_fleet_table(N)
    table["policy"]["safety"] = "none"
    bare = write_fleet_scenario(tmp, table, "no_safety.toml")
    gt, gen = tmp / "ground_truth", tmp / "generator" / "generator.pt"
    args = ["--data", str(gt), "--generator", str(gen), "--policy", str(tmp / "policy/policy.pt")]
    assert main(["evaluate", str(bare), *args, "--out", str(tmp / "ev_none"), "--quiet"]) == 0
    for folder, want in (("evaluation", "sumo"), ("ev_none", "none")):
        safety = pd.read_csv(tmp / folder / "safety.csv")
        manifest = json.loads((tmp / folder / "evaluation_manifest.json").read_text())
        assert manifest["safety"] == want, folder
        # the default adds the policy alone (safety none) beside each policy row
        assert set(safety["safety"]) == ({"sumo", "none"} if want == "sumo" else {"none"})
        if want == "none":
            assert (safety["safety_capped"] == 0).all()
            assert (safety["hidden_steps"] > 0).all()
            assert len(safety) == len(pd.read_csv(tmp / "evaluation" / "safety.csv")) - 2

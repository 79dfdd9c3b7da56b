"""Hidden sets per snapshot on a section (``instrumented.hidden = "snapshot"``, issue 16): the
ring's protocol on the section wing. A small real run: the ring's IDM fleet (4 vehicles) as the
demand of the ring network read as a closed one-lane section, every vehicle recorded."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import bremen_files_with
from fleet_scenarios import small_fleet_table, write_fleet_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import (
    hide_random,
    recorded_snapshots,
    section_snapshots,
    snapshots_by_k,
    split_runs,
)
from macromicro_sumo.env.section_bank import build_section_bank
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.section import micro_pairs
from macromicro_sumo.generator.section_stage import stage_snapshots
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

N_VEHICLES = 4


def fleet_table(hidden: str = "snapshot", seed: int = 2024) -> dict:
    """The ring_paper_section scenario, small: 4 vehicles, 4 runs of 60 s, 30 s intervals."""
    table = small_fleet_table(
        N_VEHICLES, 4, hidden, policy={"observation": "paper"}, evaluation={"fcd_episodes": 1}
    )
    return {**table, "name": "ring_snapshot_sets", "seed": seed}


def write(folder: Path, table: dict, name: str = "scenario.toml") -> Path:
    return write_fleet_scenario(folder, table, name)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(scenario, folder) of the stages up to the evaluation (no deployment)."""
    tmp = tmp_path_factory.mktemp("snapshot_sets")
    path = write(tmp, fleet_table())
    gt, gen, pol, ev = (tmp / d for d in ("gt", "gen", "pol", "ev"))
    q = ["--quiet"]
    assert main(["simulate", str(path), "--out", str(gt), *q]) == 0
    assert main(["train-generator", str(path), "--data", str(gt), "--out", str(gen), *q]) == 0
    gen_pt = str(gen / "generator.pt")
    args = ["--data", str(gt), "--generator", gen_pt]
    assert main(["train-policy", str(path), *args, "--out", str(pol), *q]) == 0
    pol_pt = str(pol / "policy.pt")
    assert main(["evaluate", str(path), *args, "--policy", pol_pt, "--out", str(ev), *q]) == 0
    return path, tmp


def test_hidden_sets_are_drawn_per_snapshot_within_the_range(run) -> None:
    path, tmp = run
    sc = load_scenario(path)
    truth = load_section_truth(tmp / "gt", sc)
    recorded = recorded_snapshots(truth, sc, truth.runs)
    assert (recorded.valid.sum(axis=1) == N_VEHICLES).all()  # closed: the whole fleet
    snaps = section_snapshots(truth, sc, truth.runs)  # Stage II's: policy.hidden_train
    hidden = snaps.valid & ~snaps.observed
    k = hidden.sum(axis=1)
    assert (k == snaps.k_true).all()
    assert set(k.tolist()) == {1, 2, 3}  # every K of [1, 3], none outside
    # The truth's instrumented set is one per run; here two snapshots of one run at the
    # same K hide different vehicles.
    run0 = snaps.run == snaps.run[0]
    sets = {
        tuple(np.flatnonzero(h)) for h, kk in zip(hidden[run0], k[run0], strict=True) if kk == 1
    }
    assert len(sets) > 1
    # The detectors' vehicle count stays what it was: k_est + observed is unchanged.
    before = recorded.k_est + recorded.observed.sum(axis=1)
    assert (snaps.k_est == np.maximum(0, before - snaps.observed.sum(axis=1))).all()


def test_hidden_sets_are_seeded(run) -> None:
    path, tmp = run
    sc = load_scenario(path)
    truth = load_section_truth(tmp / "gt", sc)
    again = load_scenario(write(tmp, fleet_table(), "again.toml"))
    other = load_scenario(write(tmp, fleet_table(seed=7), "other.toml"))
    a = section_snapshots(truth, sc, truth.runs)
    b = section_snapshots(truth, again, truth.runs)
    c = section_snapshots(truth, other, truth.runs)
    assert (a.observed == b.observed).all()
    assert (a.observed != c.observed).any()
    base = recorded_snapshots(truth, sc, truth.runs)
    by_k, by_k_again = snapshots_by_k(base, range(1, 4), 5), snapshots_by_k(base, range(1, 4), 5)
    for k, s in by_k.items():
        assert ((s.valid & ~s.observed).sum(axis=1) == k).all()
        assert (s.observed == by_k_again[k].observed).all()
    assert (by_k[1].observed != snapshots_by_k(base, range(1, 2), 6)[1].observed).any()
    with pytest.raises(UserError, match="cannot hide 5 of its 4 vehicles"):
        hide_random(base, 5, np.random.default_rng(0))


def test_default_keeps_the_instrumented_vehicles(run) -> None:
    """hidden = "run" (the default): the truth's instrumented vehicles are the observed ones,
    the bank replays only them and the micro pairs are theirs."""
    path, tmp = run
    table = fleet_table()
    del table["instrumented"]["hidden"]
    sc = load_scenario(write(tmp, table, "default.toml"))
    assert sc.instrumented.hidden == "run"
    truth = load_section_truth(tmp / "gt", sc)
    snaps = section_snapshots(truth, sc, truth.runs)
    traj = truth.trajectories.set_index(["run", "time_s", "arc_m"])["observed"]
    for i in range(0, len(snaps), 7):
        for j in np.flatnonzero(snaps.valid[i]):
            key = (snaps.run[i], snaps.time_s[i], snaps.arc_m[i, j])
            assert snaps.observed[i, j] == traj.loc[key]
    n_obs = truth.trajectories.groupby("run")["observed"].sum()
    obs, _ = micro_pairs(sc, truth, truth.runs)
    snap_sc = load_scenario(path)
    obs_all, _ = micro_pairs(snap_sc, truth, truth.runs)
    assert len(obs) < len(obs_all)  # snapshot: every recorded vehicle's pairs (the ring's)
    assert len(obs) <= n_obs.sum()

    def true_hidden(s):  # the true hidden vehicles as the completion (no generator)
        return s.lane, s.arc_m, s.speed_mps, s.valid, s.valid & ~s.observed

    bank = build_section_bank(sc, truth, snaps, true_hidden, horizon=4)
    # A bank from per-snapshot sets replays vehicles the truth did not instrument.
    snap_bank = build_section_bank(
        snap_sc, truth, section_snapshots(truth, snap_sc, truth.runs), true_hidden, horizon=4
    )
    assert (
        bank.observed.sum(axis=1)
        == truth.k_estimate.set_index(["run", "time_s"])
        .loc[list(zip(bank.run, bank.time_s, strict=True)), "n_observed"]
        .to_numpy()
    ).all()
    assert (snap_bank.hidden.sum(axis=1) >= 1).all()
    assert np.isfinite(snap_bank.gt_accel_mps2[snap_bank.observed[:, None, :].repeat(4, 1)]).all()


def test_generator_stage_judges_every_held_out_snapshot_at_every_k(run) -> None:
    path, tmp = run
    sc = load_scenario(path)
    truth = load_section_truth(tmp / "gt", sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    _, val, held = stage_snapshots(sc, truth, splits)
    n_held = len(recorded_snapshots(truth, sc, splits["held_out"]))
    assert len(held) == 3 * n_held
    assert np.bincount(held.k_true).tolist() == [0, n_held, n_held, n_held]
    assert set(val.k_true.tolist()) <= set(range(N_VEHICLES + 1))
    metrics = pd.read_csv(tmp / "gen" / "generator_metrics.csv")
    gen = metrics[metrics["method"] == "generator"]
    assert sorted(gen["k_true"].unique()) == [1, 2, 3]
    assert (gen["k_used"] == gen["k_true"]).all()
    manifest = json.loads((tmp / "gen" / "generator_manifest.json").read_text())
    assert {"generator_K1", "generator_K3", "uniform_K2"} <= set(manifest["summary"])


def test_evaluation_writes_the_per_k_table(run) -> None:
    path, tmp = run
    sc = load_scenario(path)
    truth = load_section_truth(tmp / "gt", sc)
    by_k = pd.read_csv(tmp / "ev" / "macro_alignment_by_k.csv")
    for col in (
        "hidden_count",
        "K",
        "method",
        "mean_speed_mps",
        "mean_speed_err_mps",
        "speed_err_ci_lo_mps",
        "speed_err_ci_hi_mps",
        "std_speed_mps",
        "std_spacing_m",
        "spacing_std_err_pct",
        "spacing_std_err_ci_lo_pct",
        "spacing_std_err_ci_hi_pct",
        "collisions",
        "episodes",
    ):
        assert col in by_k.columns, col
    methods = {"ground_truth", "policy", "idm_calibrated", "idm_true"}  # a fleet: the oracle too
    for label in ("estimated", "true"):
        rows = by_k[by_k["hidden_count"] == label]
        assert sorted(rows["K"].unique()) == [1, 2, 3]
        for _, g in rows.groupby("K"):
            assert set(g["method"]) == methods
    gt = by_k[by_k["method"] == "ground_truth"]
    assert (gt["mean_speed_err_mps"] == 0).all() and (gt["spacing_std_err_pct"] == 0).all()
    # Every held-out snapshot with a recorded future (4 steps) at every K, pooled in
    # macro_alignment.csv: the per-K episodes add up to the pooled row's.
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    held = recorded_snapshots(truth, sc, splits["held_out"])
    n = int((held.time_s + 4 * 0.5 <= 60.0 - 0.5 + 1e-6).sum())
    true = by_k[(by_k["hidden_count"] == "true") & (by_k["method"] == "policy")]
    assert (true["episodes"] == n).all()
    align = pd.read_csv(tmp / "ev" / "macro_alignment.csv")
    pooled = align[(align["hidden_count"] == "true") & (align["method"] == "policy")]
    assert int(pooled["episodes"].iloc[0]) == 3 * n
    assert int(pooled["collisions"].iloc[0]) == int(true["collisions"].sum())
    assert float(pooled["mean_k"].iloc[0]) == pytest.approx(2.0)
    manifest = json.loads((tmp / "ev" / "evaluation_manifest.json").read_text())
    assert manifest["hidden"] == "snapshot" and manifest["episodes_by_k"] == {
        "1": n,
        "2": n,
        "3": n,
    }


def test_snapshot_sets_refuse_bad_ranges_and_field_data(tmp_path: Path) -> None:
    table = fleet_table()
    table["generator"]["hidden_eval"] = [0, 3]
    with pytest.raises(UserError, match=r"generator.hidden_eval = \[0, 3\] starts at 0"):
        load_scenario(write(tmp_path, table))
    table = fleet_table()
    table["generator"]["hidden_train"] = [3, 1]
    with pytest.raises(UserError, match=r"generator.hidden_train = \[3, 1\] is reversed"):
        load_scenario(write(tmp_path, table))
    table = fleet_table(hidden="every")
    with pytest.raises(UserError, match="instrumented.hidden"):
        load_scenario(write(tmp_path, table))
    # Field data records the instrumented vehicles only: nothing else to hide.
    files = bremen_files_with(tmp_path, "").read_text()
    files = files.replace("[instrumented]\n", '[instrumented]\nhidden = "snapshot"\n', 1)
    (tmp_path / "files.toml").write_text(files)
    with pytest.raises(UserError, match=r"field data records the instrumented ones only"):
        load_scenario(tmp_path / "files.toml")

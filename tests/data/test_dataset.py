"""The Stage I dataset against a real (small) ground truth: run splits, snapshots, hidden
masks and the macro descriptor Psi each snapshot carries."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import write_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.data.macro import PSI_COLUMNS
from macromicro_sumo.data.ring import (
    GroundTruth,
    held_out_by_k,
    hide,
    load_ground_truth,
    psi_for,
    run_arrays,
    snapshot_states,
    split_runs,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import file_sha256
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.ring import Scenario

L = 2 * math.pi * 100.0
N = 5
N_RUNS = 4
DURATION_S = 120.0
CSV_ATOL = 2e-6  # CSVs hold 6 decimals


@pytest.fixture(scope="module")
def gt_small(tmp_path_factory) -> tuple[Scenario, GroundTruth]:
    """The paper ring, 4 runs of 120 s (two 60 s detector intervals), simulated once."""
    folder = tmp_path_factory.mktemp("gt")
    path = write_scenario(
        folder, {"simulation.n_runs": N_RUNS, "simulation.duration_s": DURATION_S}
    )
    out = folder / "out"
    assert main(["simulate", str(path), "--out", str(out), "--quiet"]) == 0
    sc = load_scenario(path)
    return sc, load_ground_truth(out, sc)


def with_generator(sc: Scenario, **changes) -> Scenario:
    return dataclasses.replace(sc, generator=dataclasses.replace(sc.generator, **changes))


def ring_gaps_np(arc: np.ndarray, length: float = L) -> np.ndarray:
    """Gaps between consecutive vehicles in arc order, per row."""
    s = np.sort(np.mod(arc, length), axis=-1)
    return np.mod(np.roll(s, -1, axis=-1) - s, length)


# --------------------------------------------------------------------------- split_runs


@pytest.mark.parametrize("n_runs", [2, 3, 4, 7, 20, 40])
@pytest.mark.parametrize("seed", [0, 2024])
def test_split_runs_is_a_disjoint_cover(n_runs, seed):
    runs = np.arange(n_runs) + 100  # ids need not start at 0
    parts = split_runs(runs, 0.25, seed)
    assert set(parts) == {"train", "val", "held_out"}
    all_ids = np.concatenate(list(parts.values()))
    assert len(all_ids) == n_runs and set(all_ids) == set(runs.tolist())  # disjoint and covering
    assert len(parts["held_out"]) >= 1 and len(parts["train"]) >= 1
    assert len(parts["held_out"]) == max(1, round(0.25 * n_runs))
    assert len(parts["val"]) == (0 if n_runs < 3 else max(1, round(0.15 * n_runs)))
    for ids in parts.values():
        assert list(ids) == sorted(ids)


def test_split_runs_is_seeded():
    runs = np.arange(40)
    a = split_runs(runs, 0.25, 1)
    assert all(np.array_equal(a[k], split_runs(runs, 0.25, 1)[k]) for k in a)
    # Another seed -> another held-out set (10 of 40: equal sets are astronomically rare).
    assert not np.array_equal(a["held_out"], split_runs(runs, 0.25, 2)["held_out"])
    assert len(a["held_out"]) == 10 and len(a["val"]) == 6 and len(a["train"]) == 24


def test_split_runs_needs_two_runs():
    with pytest.raises(UserError, match="at least 2 ground-truth runs"):
        split_runs(np.array([0]), 0.25, 0)


def test_held_out_snapshots_come_from_held_out_runs_only(gt_small):
    sc, gt = gt_small
    parts = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)
    seen = {}
    for name, ids in parts.items():
        if len(ids):
            seen[name] = set(snapshot_states(gt, sc, ids).run.tolist())
            assert seen[name] == set(ids.tolist())
    assert not seen["held_out"] & (seen["train"] | seen.get("val", set()))


# --------------------------------------------------------------------------- snapshots


def test_snapshots_are_the_recorded_ring_states(gt_small):
    sc, gt = gt_small
    snaps = snapshot_states(gt, sc, gt.runs)
    every = sc.generator.snapshot_every_s
    # 5 s apart inside the two complete 60 s intervals: t = 5, 10, ..., 115 (t = 0 is not recorded).
    per_run = int(DURATION_S / every) - 1
    assert len(snaps) == N_RUNS * per_run
    assert snaps.arc_m.shape == snaps.speed_mps.shape == (len(snaps), N)
    assert snaps.psi.shape == (len(snaps), len(PSI_COLUMNS))
    np.testing.assert_allclose(np.mod(snaps.time_s / every, 1.0), 0.0, atol=1e-9)
    assert snaps.time_s.max() < DURATION_S
    assert not snaps.hidden.any()
    assert snaps.length_m == pytest.approx(L, abs=1e-6)
    # Values are the trajectory rows at that instant, vehicle by vehicle.
    traj = gt.trajectories
    for i in (0, len(snaps) // 2, len(snaps) - 1):
        rows = traj[(traj["run"] == snaps.run[i]) & np.isclose(traj["time_s"], snaps.time_s[i])]
        rows = rows.sort_values(
            "vehicle_id", key=lambda s: s.str.len() * 1000 + s.str[1:].astype(int)
        )
        np.testing.assert_array_equal(snaps.arc_m[i], rows["arc_pos_m"].to_numpy())
        np.testing.assert_array_equal(snaps.speed_mps[i], rows["speed_mps"].to_numpy())


def test_snapshot_spacings_sum_to_the_ring_length(gt_small):
    sc, gt = gt_small
    snaps = snapshot_states(gt, sc, gt.runs)
    gaps = ring_gaps_np(snaps.arc_m)
    np.testing.assert_allclose(gaps.sum(axis=1), L, atol=1e-6)
    assert (gaps > sc.fleet.length_m).all(), "vehicles overlap in a snapshot"
    assert np.isclose(gaps.mean(), L / N)


def test_run_arrays_orders_vehicles_numerically():
    traj = pd.DataFrame(
        {
            "run": 0,
            "time_s": [0.5] * 3 + [1.0] * 3,
            "vehicle_id": ["v10", "v2", "v1"] * 2,
            "arc_pos_m": [10.0, 2.0, 1.0, 11.0, 3.0, 2.0],
            "speed_mps": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        }
    )
    times, arc, spd, ids = run_arrays(traj, 0)
    assert ids == ["v1", "v2", "v10"]
    np.testing.assert_array_equal(times, [0.5, 1.0])
    np.testing.assert_array_equal(arc, [[1.0, 2.0, 10.0], [2.0, 3.0, 11.0]])
    np.testing.assert_array_equal(spd, [[3.0, 2.0, 1.0], [6.0, 5.0, 4.0]])


# --------------------------------------------------------------------------- hide


@pytest.mark.parametrize("k", [0, 1, 3, N])
def test_hide_hides_exactly_k_per_snapshot(gt_small, k):
    sc, gt = gt_small
    snaps = snapshot_states(gt, sc, gt.runs)
    h = hide(snaps, k, np.random.default_rng(0))
    assert (h.hidden.sum(axis=1) == k).all()
    assert (h.k == k).all()
    # Hiding only marks: true states stay for evaluation.
    np.testing.assert_array_equal(h.arc_m, snaps.arc_m)
    np.testing.assert_array_equal(h.speed_mps, snaps.speed_mps)


def test_hide_per_snapshot_counts_and_uniform_slots(gt_small):
    sc, gt = gt_small
    snaps = snapshot_states(gt, sc, gt.runs)
    ks = np.arange(len(snaps)) % (N + 1)
    h = hide(snaps, ks, np.random.default_rng(1))
    np.testing.assert_array_equal(h.hidden.sum(axis=1), ks)
    # Which vehicles are hidden is uniform over slots: over many draws, each slot is hidden
    # with probability K / N (binomial s.d. of the share ~ 0.005 for 10^4 draws).
    big = snaps.take(np.zeros(10_000, dtype=int))
    share = hide(big, 2, np.random.default_rng(2)).hidden.mean(axis=0)
    np.testing.assert_allclose(share, 2 / N, atol=0.03)


def test_hide_is_seeded(gt_small):
    sc, gt = gt_small
    snaps = snapshot_states(gt, sc, gt.runs)
    a = hide(snaps, 2, np.random.default_rng(5)).hidden
    b = hide(snaps, 2, np.random.default_rng(5)).hidden
    c = hide(snaps, 2, np.random.default_rng(6)).hidden
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    sets = held_out_by_k(snaps, range(1, 5), seed=3)
    assert sorted(sets) == [1, 2, 3, 4]
    for k, s in sets.items():
        assert (s.k == k).all()
        np.testing.assert_array_equal(s.hidden, held_out_by_k(snaps, [k], seed=3)[k].hidden)


@pytest.mark.parametrize("k", [-1, N + 1, [0, 1, N + 2]])
def test_hide_rejects_k_outside_0_n(gt_small, k):
    sc, gt = gt_small
    snaps = snapshot_states(gt, sc, gt.runs[:1]).take(np.arange(3))
    with pytest.raises(UserError, match=rf"hidden count K must be in \[0, {N}\]"):
        hide(snaps, np.asarray(k), np.random.default_rng(0))


# --------------------------------------------------------------------------- Psi


def macro_row(gt: GroundTruth, run: int, source: str, t: float) -> pd.Series:
    m = gt.macro
    rows = m[(m["run"] == run) & (m["source"] == source) & (m["begin_s"] <= t) & (m["end_s"] > t)]
    assert len(rows) == 1
    return rows.iloc[0]


@pytest.mark.parametrize("source", ["detectors", "trajectories"])
def test_psi_is_the_macro_row_of_the_snapshot_interval(gt_small, source):
    sc, gt = gt_small
    sc = with_generator(sc, psi_source=source, bounds_source="interval")
    snaps = snapshot_states(gt, sc, gt.runs)
    for i in range(len(snaps)):
        row = macro_row(gt, snaps.run[i], source, snaps.time_s[i])
        np.testing.assert_array_equal(snaps.psi[i], row[PSI_COLUMNS].to_numpy(dtype=float))
    # Two intervals per run -> two distinct Psi per run.
    for run in gt.runs:
        assert len(np.unique(snaps.psi[snaps.run == run], axis=0)) == 2


def test_psi_from_trajectories_bounds_every_snapshot_of_its_interval(gt_small):
    """The true (trajectory) Psi bounds hold for the ground truth itself."""
    sc, gt = gt_small
    snaps = snapshot_states(gt, with_generator(sc, psi_source="trajectories"), gt.runs)
    gaps = ring_gaps_np(snaps.arc_m)
    tol = 1e-5
    assert (gaps.min(axis=1) >= snaps.psi[:, 2] - tol).all()
    assert (gaps.max(axis=1) <= snaps.psi[:, 3] + tol).all()
    assert (snaps.speed_mps.min(axis=1) >= snaps.psi[:, 4] - tol).all()
    assert (snaps.speed_mps.max(axis=1) <= snaps.psi[:, 5] + tol).all()


def test_psi_fixed_bounds_come_from_the_scenario(gt_small):
    sc, gt = gt_small
    fixed = with_generator(sc, bounds_source="fixed")
    snaps = snapshot_states(gt, fixed, gt.runs)
    interval = snapshot_states(gt, sc, gt.runs)
    np.testing.assert_array_equal(snaps.psi[:, 2:4], np.tile([115.0, 140.0], (len(snaps), 1)))
    np.testing.assert_array_equal(snaps.psi[:, 4:6], np.tile([10.5, 14.0], (len(snaps), 1)))
    # Mean speed and spacing still come from the detector interval.
    np.testing.assert_array_equal(snaps.psi[:, :2], interval.psi[:, :2])
    assert not np.array_equal(snaps.psi[:, 2:], interval.psi[:, 2:])


def test_psi_extended_bounds_widen_the_measured_range_by_range_over_n_minus_1(gt_small):
    """The detectors' n-sample extremes widened each side; the means stay measured, and
    fewer recorded gaps and speeds fall outside than outside the measured range."""
    sc, gt = gt_small
    ext = snapshot_states(gt, with_generator(sc, bounds_source="extended"), gt.runs)
    meas = snapshot_states(gt, with_generator(sc, bounds_source="interval"), gt.runs)
    np.testing.assert_array_equal(ext.psi[:, :2], meas.psi[:, :2])
    for i, t in enumerate(ext.time_s):
        n = macro_row(gt, int(ext.run[i]), "detectors", float(t))["n_samples"]
        for lo, hi in ((2, 3), (4, 5)):
            widen = (meas.psi[i, hi] - meas.psi[i, lo]) / (n - 1)
            assert widen > 0
            np.testing.assert_allclose(
                ext.psi[i, [lo, hi]], meas.psi[i, [lo, hi]] + [-widen, widen]
            )

    def outside(snaps, x, lo, hi):
        return ((x < snaps.psi[:, lo, None]) | (x > snaps.psi[:, hi, None])).mean()

    gaps = ring_gaps_np(meas.arc_m)
    assert outside(ext, gaps, 2, 3) < outside(meas, gaps, 2, 3)
    assert outside(ext, ext.speed_mps, 4, 5) <= outside(meas, meas.speed_mps, 4, 5)


def test_psi_for_a_time_outside_every_interval_names_macro_csv(gt_small):
    sc, gt = gt_small
    with pytest.raises(UserError, match=r"macro\.csv: no detectors row for run 0 at t = 500 s"):
        psi_for(gt, sc, 0, 500.0)


# --------------------------------------------------------------------------- load_ground_truth


def test_load_ground_truth_reports_each_missing_file(gt_small, tmp_path):
    sc, gt = gt_small
    copy = tmp_path / "gt"
    shutil.copytree(gt.folder, copy, ignore=shutil.ignore_patterns("sumo"))
    (copy / "macro.csv").unlink()
    (copy / "vehicles.csv").unlink()
    with pytest.raises(UserError, match=r"missing macro\.csv, vehicles\.csv") as exc:
        load_ground_truth(copy, sc)
    assert str(copy) in str(exc.value)
    with pytest.raises(UserError, match="ground-truth folder not found"):
        load_ground_truth(tmp_path / "nope", sc)


def test_load_ground_truth_rejects_another_scenario(gt_small, tmp_path):
    sc, gt = gt_small
    other = load_scenario(
        write_scenario(
            tmp_path,
            {
                "fleet.n_vehicles": 4,
                "bounds.spacing_m": [115.0, 160.0],
                "generator.hidden_train": [0, 4],
                "generator.hidden_eval": [1, 4],
            },
        )
    )
    with pytest.raises(UserError, match=r"fleet\.n_vehicles = 5, scenario .* has 4"):
        load_ground_truth(gt.folder, other)


def legacy_copy(gt: GroundTruth, folder: Path) -> Path:
    """A copy of ``gt`` whose manifest has no outputs map, as folders written before it."""
    shutil.copytree(gt.folder, folder, ignore=shutil.ignore_patterns("sumo"))
    manifest = json.loads((folder / "manifest.json").read_text())
    del manifest["outputs"]
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def test_load_ground_truth_rejects_an_unreadable_csv(gt_small, tmp_path):
    sc, gt = gt_small
    copy = legacy_copy(gt, tmp_path / "gt")
    (copy / "macro.csv").write_bytes(b"")
    with pytest.raises(UserError, match=r"macro\.csv: not a readable CSV"):
        load_ground_truth(copy, sc)


def test_manifest_records_rows_and_hash_of_every_csv(gt_small):
    _, gt = gt_small
    outputs = gt.manifest["outputs"]
    csvs = sorted(p.name for p in gt.folder.glob("*.csv") if not p.name.startswith("export_"))
    assert sorted(n for n in outputs if n.endswith(".csv")) == csvs
    for name in csvs:
        assert outputs[name]["rows"] == len(pd.read_csv(gt.folder / name)), name
        assert outputs[name]["sha256"] == file_sha256(gt.folder / name), name
    assert "manifest.json" not in outputs


@pytest.mark.parametrize("name", ["trajectories.csv", "macro.csv", "vehicles.csv"])
def test_a_csv_cut_mid_row_is_refused_by_name(gt_small, tmp_path, name):
    sc, gt = gt_small
    copy = tmp_path / "gt"
    shutil.copytree(gt.folder, copy, ignore=shutil.ignore_patterns("sumo"))
    data = (copy / name).read_bytes()
    (copy / name).write_bytes(data[: len(data) // 2])  # a kill or full disk while copying
    rows = gt.manifest["outputs"][name]["rows"]
    with pytest.raises(UserError, match=rf"{name}: \d+ data rows, .* records {rows} "):
        load_ground_truth(copy, sc)


def test_a_csv_edited_in_place_is_refused_by_name(gt_small, tmp_path):
    sc, gt = gt_small
    copy = tmp_path / "gt"
    shutil.copytree(gt.folder, copy, ignore=shutil.ignore_patterns("sumo"))
    text = (copy / "macro.csv").read_text()
    (copy / "macro.csv").write_text(text.replace("detectors", "detectorz", 1))
    with pytest.raises(UserError, match=r"macro\.csv: content differs from .*edited or corrupt"):
        load_ground_truth(copy, sc)


def test_a_folder_without_outputs_map_still_loads(gt_small, tmp_path):
    sc, gt = gt_small
    old = load_ground_truth(legacy_copy(gt, tmp_path / "gt"), sc)
    pd.testing.assert_frame_equal(old.trajectories, gt.trajectories)


def test_cli_train_generator_on_a_cut_trajectory_file_is_one_line(gt_small, tmp_path, capsys):
    sc, gt = gt_small
    copy = tmp_path / "gt"
    shutil.copytree(gt.folder, copy, ignore=shutil.ignore_patterns("sumo"))
    data = (copy / "trajectories.csv").read_bytes()
    (copy / "trajectories.csv").write_bytes(data[: len(data) * 2 // 3 + 7])
    out = tmp_path / "gen"
    code = main(["train-generator", sc.source, "--data", str(copy), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
    assert f"{copy / 'trajectories.csv'}: " in err and "Traceback" not in err
    assert not out.exists() or not any(out.iterdir())


def test_ground_truth_runs_are_sorted_unique(gt_small):
    _, gt = gt_small
    assert list(gt.runs) == list(range(N_RUNS))
    assert isinstance(gt.folder, Path)


def stage_fails(capsys, sc: Scenario, data: Path, out: Path, *fragments: str) -> str:
    """``train-generator`` on a bad ground truth: exit 2, one line, ``out`` never written."""
    code = main(["train-generator", sc.source, "--data", str(data), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    assert not out.exists()
    return err


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", ""])
def test_invalid_manifest_is_one_line(gt_small, tmp_path, capsys, text):
    sc, gt = gt_small
    copy = tmp_path / "gt"
    shutil.copytree(gt.folder, copy, ignore=shutil.ignore_patterns("sumo"))
    (copy / "manifest.json").write_text(text)
    stage_fails(capsys, sc, copy, tmp_path / "gen", f"{copy / 'manifest.json'}: ")


@pytest.mark.parametrize(
    ("name", "column"),
    [("trajectories.csv", "speed_mps"), ("macro.csv", "source"), ("vehicles.csv", "tau_s")],
)
def test_a_missing_column_is_one_line(gt_small, tmp_path, capsys, name, column):
    sc, gt = gt_small
    copy = legacy_copy(gt, tmp_path / "gt")
    df = pd.read_csv(copy / name)
    df.drop(columns=column).to_csv(copy / name, index=False)
    stage_fails(capsys, sc, copy, tmp_path / "gen", f"{copy / name}: missing column(s) {column}")


@pytest.mark.parametrize("value", [float("nan"), float("inf"), "fast"])
def test_non_finite_trajectories_are_one_line(gt_small, tmp_path, capsys, value):
    """A NaN, inf or word in a state was a ValueError stages later, after the log began."""
    sc, gt = gt_small
    copy = legacy_copy(gt, tmp_path / "gt")
    df = pd.read_csv(copy / "trajectories.csv")
    df["speed_mps"] = df["speed_mps"].astype(object)
    df.loc[7, "speed_mps"] = value
    df.to_csv(copy / "trajectories.csv", index=False)
    stage_fails(capsys, sc, copy, tmp_path / "gen", "trajectories.csv: column speed_mps", "line 9")

"""The deployment comparison: GEH, RMSE, shares and W1 against hand-computed values, headway
and TTC on a hand-made trajectory, and the comparison of real ground-truth folders (a
folder against itself, against another seed, against an edited copy)."""

from __future__ import annotations

import math
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import NETS, ROOT, SMALL, dump_toml, write_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.deploy.compare import (
    ALL_LANES,
    COMPARISON_COLUMNS,
    DETECTOR_INTERVAL_COLUMNS,
    SUMMARY_COLUMNS,
    acted_shares,
    compare_folders,
    detector_scores,
    geh,
    rmse,
    station_table,
    write_comparison,
)
from macromicro_sumo.deploy.distributions import (
    lane_trajectories,
    samples,
    time_headways,
    times_to_collision,
    w1,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario

RING = NETS / "ring_r100_e4.net.xml"

# --------------------------------------------------------------------------- statistics


def test_geh_against_hand_computed_values() -> None:
    got = geh(np.array([300.0, 100.0, 0.0, 1000.0, np.nan]), np.array([200.0, 0.0, 0.0, 1000.0, 5]))
    # sqrt(2 * 100^2 / 500) = sqrt(40); sqrt(2 * 100^2 / 100) = sqrt(200); both zero: 0.
    np.testing.assert_allclose(got[:4], [math.sqrt(40.0), math.sqrt(200.0), 0.0, 0.0])
    assert np.isnan(got[4])


def test_rmse_skips_missing_pairs() -> None:
    assert rmse(np.array([1.0, 2.0, 3.0]), np.array([1.0, 4.0, np.nan])) == pytest.approx(
        math.sqrt(2.0)
    )
    assert np.isnan(rmse(np.array([np.nan]), np.array([1.0])))


def test_detector_scores_on_a_hand_made_comparison() -> None:
    comp = pd.DataFrame(
        {
            "lane": [ALL_LANES] * 5 + [0],
            "geh": [0.0, 4.9, 5.0, 7.0, np.nan, 99.0],
            "speed_truth_mps": [20.0, 20.0, 10.0, np.nan, np.nan, 1.0],
            "speed_method_mps": [21.0, 19.0, 10.4, 12.0, np.nan, 9.0],
            "density_truth_vpkm": [10.0, 20.0, 30.0, 40.0, 0.0, 1.0],
            "density_method_vpkm": [13.0, 16.0, 30.0, 40.0, 0.0, 50.0],
        }
    )
    s = detector_scores(comp)
    assert s["station_intervals"] == 5  # the lane row is not a station-interval
    assert s["share_geh_below_5"] == pytest.approx(2 / 4)  # 0 and 4.9 of four flows
    # Speeds measured on 4 station-intervals: 21/20 (+5%), 19/20 (-5%) and 10.4/10 (+4%)
    # are within 5%; a speed on the method's side only is a miss; none on either: not counted.
    assert s["share_speed_within_5pct"] == pytest.approx(3 / 4)
    assert s["mean_geh"] == pytest.approx((0 + 4.9 + 5 + 7) / 4)
    assert s["speed_rmse_mps"] == pytest.approx(math.sqrt((1 + 1 + 0.16) / 3))
    assert s["speed_bias_mps"] == pytest.approx((1 - 1 + 0.4) / 3)
    assert s["density_rmse_vpkm"] == pytest.approx(math.sqrt((9 + 16) / 5))


def test_w1_of_known_samples() -> None:
    assert w1(np.array([0.0, 1.0, 3.0]), np.array([5.0, 6.0, 8.0])) == pytest.approx(5.0)
    assert w1(np.array([0.0, 1.0]), np.array([0.0, 3.0])) == pytest.approx(1.0)
    assert np.isnan(w1(np.array([]), np.array([1.0])))


def test_headway_and_ttc_of_a_two_vehicle_trajectory() -> None:
    # Follower at 100 m doing 20 m/s behind a 5 m leader at 130 m doing 15 m/s: gap 25 m,
    # headway 25 / 20 = 1.25 s, TTC 25 / (20 - 15) = 5 s. A second later the follower is
    # slower than its leader (no TTC); the vehicle on lane 1 is nobody's leader on lane 0.
    traj = pd.DataFrame(
        {
            "run": 0,
            "time_s": [1.0, 1.0, 1.0, 2.0, 2.0],
            "vehicle_id": ["f", "l", "x", "f", "l"],
            "vtype": ["car", "car", "car", "car", "car"],
            "lane_index": [0, 0, 1, 0, 0],
            "arc_m": [100.0, 130.0, 120.0, 110.0, 150.0],
            "speed_mps": [20.0, 15.0, 30.0, 10.0, 15.0],
            "accel_mps2": 0.0,
        }
    )
    lanes = lane_trajectories(traj, None, {"car": 5.0})
    np.testing.assert_allclose(lanes["gap_m"].to_numpy(), [25.0, np.nan, np.nan, 35.0, np.nan])
    np.testing.assert_allclose(lanes["leader_speed_mps"], [15.0, np.nan, np.nan, 15.0, np.nan])
    s = samples(lanes)
    np.testing.assert_allclose(s["headway_s"], [1.25, 3.5])
    np.testing.assert_allclose(s["ttc_s"], [5.0])
    # Slow vehicles have no headway; TTC beyond the cap is left out.
    assert time_headways(np.array([2.0]), np.array([0.4])).size == 0
    assert times_to_collision(np.array([100.0]), np.array([11.0]), np.array([10.0])).size == 0


def test_closed_section_leader_wraps_around_the_loop() -> None:
    section = read_section(RING, ["e0", "e1", "e2", "e3"], closed=True)
    traj = pd.DataFrame(
        {
            "run": 0,
            "time_s": 0.0,
            "vehicle_id": ["a", "b"],
            "vtype": "car",
            "lane_index": 0,
            "arc_m": [10.0, 600.0],
            "speed_mps": [5.0, 8.0],
            "accel_mps2": 0.0,
        }
    )
    lanes = lane_trajectories(traj, section, {"car": 4.0})
    # b at 600 m follows a at 10 m around the loop of 2 pi 100 m: its gap is the spacing
    # 10 + L - 600 minus a's 4 m; a follows b 590 m ahead.
    np.testing.assert_allclose(lanes["gap_m"], [586.0, 10.0 + section.length_m - 600.0 - 4.0])
    np.testing.assert_allclose(lanes["leader_speed_mps"], [8.0, 5.0])


def test_station_aggregates_the_lanes_of_one_position() -> None:
    det = pd.DataFrame(
        {
            "run": 0,
            "detector_id": ["a", "b", "c"],
            "kind": "e1",
            "lane_index": [0, 1, 0],
            "arc_m": [500.0, 502.0, 900.0],
            "begin_s": 0.0,
            "end_s": 30.0,
            "n_veh": [5, 10, 0],
            "flow_vph": [600.0, 1200.0, 0.0],
            "speed_mps": [20.0, 30.0, np.nan],
            "density_vpkm": [600 / 20 / 3.6, 1200 / 30 / 3.6, 0.0],
        }
    )
    st = station_table(det)
    one = st[(st["station"] == "e1_501m") & (st["lane"] == ALL_LANES)].iloc[0]
    assert one["flow_vph"] == pytest.approx(1800.0)
    # Space-mean speed of the 15 vehicles: 15 / (5 / 20 + 10 / 30).
    assert one["speed_mps"] == pytest.approx(15 / (5 / 20 + 10 / 30))
    assert one["density_vpkm"] == pytest.approx(600 / 72 + 1200 / 108)
    assert sorted(st.loc[st["station"] == "e1_501m", "lane"]) == [ALL_LANES, 0, 1]
    # A one-lane station has its station row only.
    assert st.loc[st["station"] == "e1_900m", "lane"].tolist() == [ALL_LANES]
    assert np.isnan(st.loc[st["station"] == "e1_900m", "speed_mps"].iloc[0])


# --------------------------------------------------------------------------- real folders


@pytest.fixture(scope="module")
def rings(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two ground truths of the paper ring, 3 runs of 120 s, seeds 42 and 99."""
    folder = tmp_path_factory.mktemp("rings")
    outs = []
    for seed in (None, 99):
        over = {**SMALL, "simulation.n_runs": 3, **({"seed": seed} if seed else {})}
        path = write_scenario(folder / f"s{seed}", over)
        out = folder / f"gt{seed}"
        assert main(["simulate", str(path), "--out", str(out), "--quiet"]) == 0
        outs.append(out)
    return outs[0], outs[1]


@pytest.fixture(scope="module")
def corridor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The netgen corridor example (lane counts 2-1-3-1-2-3-1), 2 short runs."""
    folder = tmp_path_factory.mktemp("corridor")
    table = tomllib.loads((ROOT / "scenarios" / "netgen_corridor.toml").read_text())
    table["network"]["sumocfg"] = str(ROOT / "sumo_nets" / "netgen_corridor" / "corridor.sumocfg")
    table["simulation"].update(warmup_s=150.0, duration_s=90.0, n_runs=2)
    table["detectors"]["interval_s"] = 30.0
    path = folder / "corridor.toml"
    path.write_text(dump_toml(table))
    assert main(["simulate", str(path), "--out", str(folder / "gt"), "--quiet"]) == 0
    return folder / "gt"


def test_a_ring_compared_with_itself_agrees_everywhere(rings: tuple[Path, Path]) -> None:
    truth, _ = rings
    comp, summary = compare_folders(truth, {"self": truth})
    assert list(comp.columns) == COMPARISON_COLUMNS
    assert list(summary.columns) == SUMMARY_COLUMNS
    s = summary.iloc[0]
    # 3 runs x 8 stations (an E1 at mid-edge and an E2 over each of the 4 edges: the ring's
    # detector file, read as a section's) x 2 full intervals of 60 s
    assert (s["runs"], s["station_intervals"]) == (3, 48)
    assert (s["share_geh_below_5"], s["share_speed_within_5pct"]) == (1.0, 1.0)
    assert (s["speed_rmse_mps"], s["density_rmse_vpkm"], s["mean_geh"]) == (0.0, 0.0, 0.0)
    assert s["w1_speed_mps"] == 0.0 and s["w1_headway_s"] == 0.0
    assert (s["collisions"], s["teleports"], s["truth_collisions"]) == (0, 0, 0)
    assert np.isnan(s["emergency_brakings"])  # the truth's runs.csv does not record them


def test_another_seed_differs_and_an_edited_copy_scores_as_edited(
    rings: tuple[Path, Path], tmp_path: Path
) -> None:
    truth, other = rings
    # A stand-in deployment: the held-out runs 1 and 2 only, every loop 10% faster, with
    # the safety columns a deployment adds.
    edited = tmp_path / "edited"
    shutil.copytree(truth, edited)
    det = pd.read_csv(edited / "detectors.csv")
    det = det[det["run"] > 0]
    det["speed_mps"] *= 1.1  # every loop (E1 and E2: each a station of the section)
    det.to_csv(edited / "detectors.csv", index=False)
    runs = pd.read_csv(edited / "runs.csv").query("run > 0")
    runs.assign(
        collisions=[1, 2], emergency_brakings=[3, 0], vehicle_steps_driven=[100, 50]
    ).assign(floor_acted=[12, 3]).to_csv(edited / "runs.csv", index=False)
    comp, summary = compare_folders(truth, {"other": other, "edited": edited})
    o, e = summary.set_index("method").loc["other"], summary.set_index("method").loc["edited"]
    assert o["runs"] == 3 and o["speed_rmse_mps"] > 0 and o["w1_speed_mps"] > 0
    assert e["runs"] == 2 and e["station_intervals"] == 32
    assert (e["share_geh_below_5"], e["share_speed_within_5pct"]) == (1.0, 0.0)
    assert e["density_rmse_vpkm"] == 0.0
    rel = comp.loc[comp["method"] == "edited", "speed_rel_error"]
    np.testing.assert_allclose(rel.dropna(), 0.1, atol=1e-9)
    assert (e["collisions"], e["emergency_brakings"], e["vehicle_steps_driven"]) == (3, 3, 150)
    assert np.isnan(e["safety_acted"]) and np.isnan(e["safety_acted_share"])
    # The floor's count over the runs, and as a share of the driven vehicle-steps.
    assert (e["floor_acted"], e["floor_acted_share"]) == (15, 15 / 150)
    assert np.isnan(o["floor_acted_share"])  # a ground truth: nothing driven, not recorded


def test_acted_shares_are_of_the_driven_vehicle_steps() -> None:
    counts = {"vehicle_steps_driven": 400.0, "safety_acted": 30.0, "floor_acted": 2.0}
    assert acted_shares(counts) == {"safety_acted_share": 0.075, "floor_acted_share": 0.005}
    # A method that drives nobody (the oracle, a vType switch) has no share, not 0/0.
    none = acted_shares({**counts, "vehicle_steps_driven": 0.0, "floor_acted": 0.0})
    assert all(np.isnan(v) for v in none.values())


def test_a_multilane_corridor_compared_with_itself(corridor: Path, tmp_path: Path) -> None:
    comp_path, summary_path = write_comparison(corridor, {"policy": corridor}, tmp_path)
    comp, summary = pd.read_csv(comp_path), pd.read_csv(summary_path)
    s = summary.iloc[0]
    assert (s["share_geh_below_5"], s["share_speed_within_5pct"]) == (1.0, 1.0)
    assert (s["speed_rmse_mps"], s["density_rmse_vpkm"]) == (0.0, 0.0)
    assert s["w1_ttc_s"] == 0.0 and s["w1_accel_mps2"] == 0.0
    assert (comp["geh"] == 0).all()
    # A three-lane station: its row is the sum of its loops' flows, and each lane has its own.
    det = pd.read_csv(corridor / "detectors.csv")
    per_pos = det.groupby(["run", "arc_m", "begin_s"])
    lanes = per_pos["lane_index"].nunique()
    (run, arc, begin), _ = next((k, n) for k, n in lanes.items() if n == 3)
    row = comp[
        (comp["run"] == run)
        & (comp["arc_m"] == arc)
        & (comp["begin_s"] == begin)
        & (comp["lane"] == ALL_LANES)
    ]
    assert row["flow_truth_vph"].item() == pytest.approx(per_pos["flow_vph"].sum()[run, arc, begin])
    assert set(comp.loc[comp["arc_m"] == arc, "lane"]) == {ALL_LANES, 0, 1, 2}


# --------------------------------------------------------------------------- comparison interval


def test_a_longer_comparison_interval_pools_a_real_truth(rings: tuple[Path, Path]) -> None:
    """deploy.compare_interval_s = 120 s on 60 s detectors: one station-interval per two,
    flows as summed counts, E1 speeds over every vehicle that passed, E2 speeds weighted by
    time on the detector; the summary keeps the 60 s shares beside the 120 s ones."""
    truth, other = rings
    comp60, s60 = compare_folders(truth, {"other": other})
    comp, s = compare_folders(truth, {"other": other}, 120.0)
    a, b = s60.iloc[0], s.iloc[0]
    assert (a["compare_interval_s"], a["detector_interval_s"]) == (60.0, 60.0)
    assert (b["compare_interval_s"], b["detector_interval_s"]) == (120.0, 60.0)
    assert (a["station_intervals"], b["station_intervals"]) == (48, 24)  # 3 runs x 8 x 2 or 1
    for col, at in DETECTOR_INTERVAL_COLUMNS.items():
        assert a[at] == a[col] and b[at] == a[col]
    assert set(comp["end_s"] - comp["begin_s"]) == {120.0}
    det = pd.read_csv(truth / "detectors.csv")
    det = det[(det["run"] == 1) & (det["end_s"] - det["begin_s"] == 60.0)]
    for kind in ("e1", "e2"):
        loop = det[det["kind"] == kind].sort_values(["arc_m", "begin_s"]).head(2)
        row = comp[
            (comp["run"] == 1)
            & (comp["station"] == f"{kind}_{loop['arc_m'].iloc[0]:.0f}m")
            & (comp["lane"] == ALL_LANES)
        ].iloc[0]
        n, v = loop["n_veh"].to_numpy(float), loop["speed_mps"].to_numpy(float)
        if kind == "e1":
            assert row["flow_truth_vph"] == pytest.approx(n.sum() * 3600 / 120)
            ok = n > 0
            assert row["speed_truth_mps"] == pytest.approx(n[ok].sum() / (n[ok] / v[ok]).sum())
        else:
            ss = loop["sampled_seconds_s"].to_numpy(float)
            assert np.isnan(row["flow_truth_vph"])
            assert row["speed_truth_mps"] == pytest.approx((ss * v).sum() / ss.sum())
        assert row["density_truth_vpkm"] == pytest.approx(loop["density_vpkm"].mean())
    # Pooling smooths when each car passes: the other seed's speeds agree better.
    assert b["speed_rmse_mps"] < a["speed_rmse_mps"]


def test_the_detectors_own_interval_gives_todays_comparison(rings: tuple[Path, Path]) -> None:
    truth, other = rings
    zero, sz = compare_folders(truth, {"other": other})
    same, ss = compare_folders(truth, {"other": other}, 60.0)
    pd.testing.assert_frame_equal(zero, same)
    pd.testing.assert_frame_equal(sz, ss)


def test_a_bad_comparison_interval_is_one_line(rings: tuple[Path, Path], tmp_path: Path) -> None:
    truth, other = rings
    with pytest.raises(UserError) as err:
        compare_folders(truth, {"other": other}, 90.0)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(truth / "detectors.csv"))
    assert "deploy.compare_interval_s = 90 is not a multiple of the detectors' interval 60" in msg
    with pytest.raises(UserError, match=r"compare_interval_s = 240 leaves no whole interval"):
        compare_folders(truth, {"other": other}, 240.0)
    path = write_scenario(tmp_path, {"deploy.compare_interval_s": 45.0})
    with pytest.raises(UserError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{path}: deploy.compare_interval_s = 45 ")
    assert msg.endswith("accepted: 0 (the detectors' own) or k x 60 s, k = 1, 2, ...")
    assert (
        load_scenario(path, {"deploy.compare_interval_s": 120.0}).deploy.compare_interval_s == 120
    )
    # Longer than a run (warm-up + duration, 180 s): refused before anything is deployed.
    with pytest.raises(UserError, match=r"deploy.compare_interval_s = 240 exceeds a run \("):
        load_scenario(path, {"deploy.compare_interval_s": 240.0})

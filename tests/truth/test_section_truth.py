"""Sections: geometry from sumolib and ground truth from a user's demand, in real SUMO.

The network is one nobody tuned for: a random corridor drawn from a seed (netgen), with
lane counts and limits that change between edges and two car-following models.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import NETS, corridor_table, dump_toml

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.leaders import lane_leaders
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.netgen import random_corridor
from macromicro_sumo.truth.section import load_section_truth, simulate_section

RING = NETS / "ring_r100_e4.net.xml"


def corridor_scenario(folder: Path, seed: int = 3, **tables: dict) -> Path:
    table = corridor_table(folder, seed) | {"generator": {"snapshot_every_s": 10.0}}
    for name, sub in tables.items():
        table.setdefault(name, {}).update(sub)
    path = folder / "corridor.toml"
    path.write_text(dump_toml(table))
    return path


@pytest.fixture(scope="module")
def corridor_truth(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("corridor")
    path = corridor_scenario(folder)
    assert main(["simulate", str(path), "--out", str(folder / "gt"), "--quiet"]) == 0
    return path, folder / "gt"


# --------------------------------------------------------------------------- geometry


def test_ring_is_a_one_lane_closed_section() -> None:
    sec = read_section(RING, ["e0", "e1", "e2", "e3"], closed=True)
    # The exact ring: 2 pi R long, four equal edges, no junction arcs.
    assert sec.length_m == pytest.approx(2 * np.pi * 100.0, abs=1e-3)
    np.testing.assert_allclose(sec.offsets_m, np.arange(4) * sec.length_m / 4, atol=1e-3)
    assert (sec.junction_m == 0).all()
    assert sec.max_lanes == 1
    arc = np.array([10.0, 300.0, 620.0])
    leader, spacing = lane_leaders(np.zeros(3, dtype=int), arc, sec.length_m, True)
    assert leader.tolist() == [1, 2, 0]
    np.testing.assert_allclose(spacing, [290.0, 320.0, 10.0 + sec.length_m - 620.0])


def test_open_section_leaders_are_per_lane() -> None:
    lane = np.array([0, 1, 0, 1, 2])
    arc = np.array([100.0, 50.0, 160.0, 70.0, 10.0])
    leader, spacing = lane_leaders(lane, arc, 1000.0, False)
    assert leader.tolist() == [2, 3, -1, -1, -1]
    np.testing.assert_allclose(
        spacing, [60.0, 20.0, NO_LEADER_GAP_M, NO_LEADER_GAP_M, NO_LEADER_GAP_M]
    )


def test_corridor_geometry_matches_the_network(tmp_path: Path) -> None:
    cor = random_corridor(tmp_path, 11)
    sec = read_section(cor.net_file, list(cor.section_edges), closed=False)
    assert tuple(sec.n_lanes) == cor.lanes_per_edge
    np.testing.assert_allclose(sec.lengths_m, cor.lengths_m, atol=0.01)
    # Every edge starts where the previous one and its junction end.
    np.testing.assert_allclose(
        sec.offsets_m[1:], (sec.offsets_m + sec.lengths_m + sec.junction_m)[:-1]
    )
    e, idx, pos = sec.to_lane(0, float(sec.offsets_m[2] + 12.5))
    lane_id = f"{sec.edge_ids[e]}_{idx}"
    assert lane_id == f"{cor.section_edges[2]}_0" and pos == pytest.approx(12.5)
    assert sec.locate(lane_id, pos) == (0, pytest.approx(sec.offsets_m[2] + 12.5))


def test_section_errors_name_the_edge(tmp_path: Path) -> None:
    cor = random_corridor(tmp_path, 11)
    edges = list(cor.section_edges)
    with pytest.raises(UserError, match="'nope' is not in"):
        read_section(cor.net_file, [edges[0], "nope"], closed=False)
    with pytest.raises(UserError, match=f"{edges[0]!r} -> {edges[2]!r} are not connected"):
        read_section(cor.net_file, [edges[0], edges[2]], closed=False)
    with pytest.raises(UserError, match="are not connected"):
        read_section(cor.net_file, edges, closed=True)  # a corridor is not a loop


# --------------------------------------------------------------------------- ground truth


def test_trajectories_obey_the_section_and_the_physics(corridor_truth: tuple[Path, Path]) -> None:
    sc_path, gt = corridor_truth
    truth = load_section_truth(gt, load_scenario(sc_path))
    sec, traj = truth.section, truth.trajectories
    assert traj["arc_m"].between(0.0, sec.length_m).all()
    e = traj["edge_index"].to_numpy()
    on_edge = traj["arc_m"].to_numpy() <= sec.offsets_m[e] + sec.lengths_m[e]
    # In a junction the lane index is the one the vehicle is heading into.
    lanes = np.where(on_edge, sec.n_lanes[e], sec.n_lanes[np.minimum(e + 1, len(sec.n_lanes) - 1)])
    assert (traj["lane_index"].to_numpy() < lanes).all()
    assert set(truth.vtypes["car_follow_model"]) == {"IDM", "Krauss"}  # recorded, not assumed
    # SUMO's Euler update: the arc advances by the new speed x dt (on one lane, off junctions).
    t = traj.sort_values(["run", "vehicle_id", "time_s"])
    same = (
        (t["vehicle_id"].to_numpy()[1:] == t["vehicle_id"].to_numpy()[:-1])
        & (np.diff(t["time_s"].to_numpy()) == pytest.approx(0.5))
        & (t["edge_index"].to_numpy()[1:] == t["edge_index"].to_numpy()[:-1])
    )
    d_arc = np.diff(t["arc_m"].to_numpy())[same]
    v_new = t["speed_mps"].to_numpy()[1:][same]
    np.testing.assert_allclose(d_arc, v_new * 0.5, atol=1e-3)
    # Vehicles enter and leave: the section is open.
    first_seen = traj.groupby("vehicle_id")["arc_m"].first()
    assert (first_seen < 30.0).mean() > 0.5


def test_detectors_agree_with_trajectories(corridor_truth: tuple[Path, Path]) -> None:
    _, gt = corridor_truth
    m = pd.read_csv(gt / "macro.csv")
    det = m[m["source"] == "detectors"].set_index(["run", "begin_s"])
    tra = m[m["source"] == "trajectories"].set_index(["run", "begin_s"])
    both = det.merge(tra, left_index=True, right_index=True, suffixes=("_d", "_t"))
    assert len(both) >= 4
    speed_err = (both["mean_speed_mps_d"] / both["mean_speed_mps_t"] - 1).abs()
    assert speed_err.mean() < 0.05
    count_err = (both["vehicles_d"] / both["vehicles_t"] - 1).abs()
    assert count_err.mean() < 0.2
    manifest = json.loads((gt / "manifest.json").read_text())
    assert manifest["detectors"]["source"] == "auto"
    assert manifest["k_estimate"]["mean_abs_error_per_lane_veh"] < 2.0


def test_k_estimate_and_instrumented_share(corridor_truth: tuple[Path, Path]) -> None:
    sc_path, gt = corridor_truth
    sc = load_scenario(sc_path)
    truth = load_section_truth(gt, sc)
    k = truth.k_estimate
    # The true hidden count, recounted from the trajectories themselves.
    traj = truth.trajectories
    hidden = traj[~traj["observed"]].groupby(["run", "time_s"]).size()
    recount = hidden.reindex(list(zip(k["run"], k["time_s"], strict=True)), fill_value=0)
    assert (k["k_true"].to_numpy() == recount.to_numpy()).all()
    assert (k["k_error"] == k["k_est"] - k["k_true"]).all()
    share = truth.trajectories.groupby("vehicle_id")["observed"].first().mean()
    assert 0.15 < share < 0.45  # penetration 0.3
    snaps = section_snapshots(truth, sc, truth.runs)
    assert 0.8 * len(k) <= len(snaps) <= len(k)  # times in a closed detector interval
    kk = k.set_index(["run", "time_s"]).loc[list(zip(snaps.run, snaps.time_s, strict=True))]
    assert (snaps.valid.sum(1) == kk["n_vehicles"].to_numpy()).all()
    assert (snaps.hidden.sum(1) == snaps.k_true).all()
    assert np.isfinite(snaps.psi[:, 0]).all() and (snaps.psi[:, 1] > 0).all()


def test_same_seed_same_bytes(corridor_truth: tuple[Path, Path], tmp_path: Path) -> None:
    sc_path, gt = corridor_truth
    simulate_section(load_scenario(sc_path), tmp_path / "again", progress=False)
    for name in ("trajectories.csv", "macro.csv", "k_estimate.csv", "detectors.csv"):
        assert (tmp_path / "again" / name).read_bytes() == (gt / name).read_bytes(), name


def test_instrumented_by_vtype_and_by_ids(tmp_path: Path) -> None:
    path = corridor_scenario(tmp_path, instrumented={"penetration": 1.0, "vtype": "car_krauss"})
    sc = load_scenario(path)
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    obs = truth.trajectories.groupby("vehicle_id").first()
    assert (obs["observed"] == (obs["vtype"] == "car_krauss")).all()


def test_user_detectors_are_used_and_placement_can_be_off(tmp_path: Path) -> None:
    cor = random_corridor(tmp_path / "net", 3)
    lane = f"{cor.section_edges[1]}_0"
    add = tmp_path / "loops.add.xml"
    add.write_text(
        f'<additional><inductionLoop id="my_loop" lane="{lane}" pos="20" period="30" '
        f'file="out.xml"/></additional>'
    )
    path = corridor_scenario(
        tmp_path, network={"additional_files": [str(add)]}, detectors={"auto_spacing_m": 0.0}
    )
    gt = simulate_section(load_scenario(path), tmp_path / "gt", progress=False)
    det = pd.read_csv(gt / "detectors.csv")
    assert set(det["detector_id"]) == {"my_loop"} and set(det["source"]) == {"user"}
    assert not (tmp_path / "out.xml").exists()  # nothing written beside the user's files
    # No user detector and placement off: a clear error before SUMO runs.
    path = corridor_scenario(tmp_path, detectors={"auto_spacing_m": 0.0})
    assert main(["simulate", str(path), "--out", str(tmp_path / "gt2"), "--quiet"]) == 2
    assert not (tmp_path / "gt2").exists()


@pytest.mark.parametrize("command", ["train-generator", "train-policy", "evaluate"])
def test_stages_refuse_a_ground_truth_of_another_step_length(
    corridor_truth: tuple[Path, Path], tmp_path: Path, capsys, command: str
) -> None:
    """The ground truth's recorded actions and replays are per step of its length: a stage of
    a scenario with another step length stops before writing anything."""
    _, gt = corridor_truth
    path = corridor_scenario(tmp_path, simulation={"step_length_s": 1.0})
    args = [command, str(path), "--data", str(gt), "--out", str(tmp_path / "o"), "--quiet"]
    if command != "train-generator":
        args += ["--generator", str(tmp_path / "generator.pt")]
    if command == "evaluate":
        args += ["--policy", str(tmp_path / "policy.pt")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err, err
    assert str(gt / "manifest.json") in err, err
    assert "simulation.step_length_s = 0.5" in err and "has 1.0" in err, err
    assert not (tmp_path / "o").exists()
    with pytest.raises(UserError, match="step_length_s"):
        load_section_truth(gt, load_scenario(path))


@pytest.mark.parametrize("name", ["vtypes.csv", "k_estimate.csv", "section.json"])
def test_section_truth_refuses_an_output_that_changed(
    corridor_truth: tuple[Path, Path], tmp_path: Path, name: str
) -> None:
    """Every file of a section's ground truth is checked against its manifest's outputs map."""
    path, gt = corridor_truth
    manifest = json.loads((gt / "manifest.json").read_text())
    assert set(manifest["outputs"]) >= {
        "section.json",
        "trajectories.csv",
        "detectors.csv",
        "macro.csv",
        "vtypes.csv",
        "k_estimate.csv",
        "runs.csv",
        "detector_passages.csv",
    }
    copy = tmp_path / "gt"
    shutil.copytree(gt, copy, ignore=shutil.ignore_patterns("sumo"))
    data = (copy / name).read_bytes()
    (copy / name).write_bytes(data[:-3])
    with pytest.raises(
        UserError, match=rf"{re.escape(str(copy / name))}: .*re-run `macromicro simulate`"
    ):
        load_section_truth(copy, load_scenario(path))
    (copy / name).unlink()
    with pytest.raises(UserError, match=rf"{re.escape(str(copy / name))}: missing"):
        load_section_truth(copy)


@pytest.mark.parametrize(
    ("name", "column", "value", "needle"),
    [
        ("trajectories.csv", "arc_m", float("nan"), "column arc_m holds 1 value(s)"),
        ("k_estimate.csv", "k_est", float("inf"), "column k_est holds 1 value(s)"),
        ("macro.csv", "source", None, "missing column(s) source"),
    ],
)
def test_section_truth_refuses_missing_columns_and_non_finite_values(
    corridor_truth: tuple[Path, Path], tmp_path: Path, name, column, value, needle
) -> None:
    _, gt = corridor_truth
    copy = tmp_path / "gt"
    shutil.copytree(gt, copy, ignore=shutil.ignore_patterns("sumo"))
    manifest = json.loads((copy / "manifest.json").read_text())
    del manifest["outputs"]  # as written before the outputs map: only the content tells
    (copy / "manifest.json").write_text(json.dumps(manifest))
    df = pd.read_csv(copy / name)
    if value is None:
        df = df.drop(columns=column)
    else:
        df[column] = df[column].astype(float)
        df.loc[0, column] = value
    df.to_csv(copy / name, index=False)
    with pytest.raises(UserError, match=re.escape(f"{copy / name}: {needle}")):
        load_section_truth(copy)

"""A ground truth from field files (``[data] source = "files"``): the round trip of a simulated
ground truth through NGSIM (0.3 m noise) and PeMS files, the scenario keys, the step grid,
station totals over the cross-section, and bad input at the CLI.

Round-trip tolerances (measured on this corridor and on scripts/export_field_data.py's
Bremen example: psi's mean speed and mean spacing within 0.03 %, K estimates equal, the
same observed vehicles and micro pairs at every snapshot):
- psi mean speed and mean spacing per snapshot within 0.5 % (PeMS rounds speeds to 0.1 mph);
- the K estimate per snapshot within 1 vehicle, on average within 0.1 (where its window of
  detector intervals lies after the simulated warm-up: the files also carry the warm-up's);
- the observed vehicles per snapshot equal; micro pairs within 1 %.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import corridor_table, dump_toml

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import PSI_FIELDS, section_snapshots
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.idm_fit import calibrate_idm, idm_policy_accel
from macromicro_sumo.evaluation.section import micro_pairs
from macromicro_sumo.fielddata.cleaning import NGSIM_CLEANING
from macromicro_sumo.fielddata.export import observed_rows
from macromicro_sumo.fielddata.schema import LEADER_COLUMNS
from macromicro_sumo.fielddata.stations import PEMS_MAPPING
from macromicro_sumo.fielddata.trajectories import NGSIM_MAPPING
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.data import (
    CleaningConfig,
    StationConventions,
    TrajectoryConventions,
    build_data,
)
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.files import (
    K_TRUE_UNKNOWN,
    data_toml,
    export_field_files,
    on_step_grid,
    spread_cross_sections,
)
from macromicro_sumo.truth.hidden_count import k_estimates
from macromicro_sumo.truth.section import load_section_truth
from macromicro_sumo.truth.section_macro import station_density

PSI_TOL = 0.005  # relative, mean speed and mean spacing per snapshot
K_TOL = 1  # vehicles per snapshot
K_MEAN_TOL = 0.1
PAIRS_TOL = 0.01
# Measured leaders (NGSIM Space_Headway with the exporter's 0.3 m radar noise; measured on
# this corridor: spacing error std 0.298 m, mean -0.003 m; derived leader speed RMSE
# 0.30 m/s; pairs' mean spacing within 0.02 % of the truth's, 3.1 x without the leader
# columns; the IDM fits' predictions 0.063 m/s^2 RMS apart on the truth's pairs).
RADAR_NOISE_M = 0.3
LEADER_SPEED_RMSE = 0.6
PAIRS_SPACING_TOL = 0.005
IDM_PRED_TOL = 0.15  # m/s^2: the files' accelerations are smoothed (sEMA), the truth's not


def write_files_scenario(folder: Path, base: dict, data: dict) -> Path:
    path = folder / "files.toml"
    path.write_text(dump_toml({**base, "name": "corridor_files"}) + "\n" + data_toml(data))
    return path


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The same recording twice: simulated, and read back from its exported files."""
    folder = tmp_path_factory.mktemp("files_truth")
    base = corridor_table(folder)
    (folder / "sim.toml").write_text(dump_toml(base))
    sim = folder / "gt_sim"
    assert main(["simulate", str(folder / "sim.toml"), "--out", str(sim), "--quiet"]) == 0
    data = export_field_files(sim, folder / "field", noise_m=0.3, seed=0)
    for kind in ("trajectories", "stations"):
        data[kind]["files"] = [str(folder / "field" / f) for f in data[kind]["files"]]
    path = write_files_scenario(folder, base, data)
    files = folder / "gt_files"
    assert main(["simulate", str(path), "--out", str(files), "--quiet"]) == 0
    return {
        "folder": folder,
        "base": base,
        "data": data,
        "sim": (load_scenario(folder / "sim.toml"), sim),
        "files": (load_scenario(path), files),
    }


def test_files_truth_is_a_ground_truth_folder(pair: dict) -> None:
    sc, gt = pair["files"]
    truth = load_section_truth(gt, sc)  # every stage loads it here
    assert truth.trajectories["observed"].all()
    assert (truth.k_estimate["k_true"] == K_TRUE_UNKNOWN).all()
    assert truth.macro["std_spacing_m"].isna().all()
    assert (truth.detectors["lane_index"] >= 0).all()
    manifest = json.loads((gt / "manifest.json").read_text())
    assert manifest["data_source"] == "files"
    assert (gt / "data_report.md").is_file() and (gt / "data_report.csv").is_file()
    assert not (gt / "detector_passages.csv").exists()
    # On the scenario's step grid, as a simulated ground truth.
    t = truth.trajectories["time_s"].to_numpy()
    assert np.allclose(t / 0.5, np.round(t / 0.5), atol=1e-6)


def test_round_trip_reproduces_psi_k_and_micro_pairs(pair: dict) -> None:
    (sa, ga), (sb, gb) = pair["sim"], pair["files"]
    ta, tb = load_section_truth(ga, sa), load_section_truth(gb, sb)
    a, b = section_snapshots(ta, sa, ta.runs), section_snapshots(tb, sb, tb.runs)
    ia = pd.DataFrame({"run": a.run, "time_s": a.time_s, "i": np.arange(len(a))})
    ib = pd.DataFrame({"run": b.run, "time_s": b.time_s, "j": np.arange(len(b))})
    with_obs = ia[(a.valid & a.observed).sum(axis=1) > 0]
    m = with_obs.merge(ib, on=["run", "time_s"])
    # Every simulated snapshot with an observed vehicle is there (the files know no other).
    assert len(m) == len(with_obs) == len(b) > 10
    for name in ("mean_speed_mps", "mean_spacing_m"):
        k = PSI_FIELDS.index(name)
        rel = np.abs(b.psi[m.j, k] / a.psi[m.i, k] - 1.0)
        assert rel.max() < PSI_TOL, (name, rel.max())
    # The station files keep the warm-up's intervals, the simulated truth drops them: K
    # averages detector intervals within k_window_s / 2 of a snapshot, so the first
    # snapshots see more intervals from files. Compared where both see the same.
    inside = m["time_s"].to_numpy() > sa.simulation.warmup_s + sa.detectors.k_window_s / 2
    # The simulated truth counts K from its loops' per-vehicle passages, which station
    # files do not carry: the files' K is compared with the simulated truth's estimate
    # from the stations' intervals alone, the same density estimate.
    dens = k_estimates(
        ta.trajectories,
        ta.macro[ta.macro["source"] == "detectors"],
        ta.section,
        sa.generator.snapshot_every_s,
        sa.detectors.k_window_s,
    )
    at = pd.MultiIndex.from_frame(m[["run", "time_s"]])
    k_a = dens.set_index(["run", "time_s"])["k_est"].reindex(at).to_numpy()
    dk = np.abs(b.k_est[m.j] - k_a)[inside]
    assert inside.sum() > 10 and dk.max() <= K_TOL and dk.mean() <= K_MEAN_TOL, dk
    n_a = (a.valid & a.observed).sum(axis=1)[m.i]
    n_b = (b.valid & b.observed).sum(axis=1)[m.j]
    np.testing.assert_array_equal(n_a, n_b)
    pa = micro_pairs(sa, ta, ta.runs, max_pairs=10**9)[1]
    pb = micro_pairs(sb, tb, tb.runs, max_pairs=10**9)[1]
    assert abs(len(pb) / len(pa) - 1.0) < PAIRS_TOL, (len(pa), len(pb))


def test_generator_stage_runs_on_files(pair: dict, tmp_path: Path) -> None:
    """Stage I on the files' ground truth, unchanged, two epochs."""
    base, data = pair["base"], pair["data"]
    path = write_files_scenario(
        tmp_path, {**base, "generator": {"epochs": 2, "batch_size": 16}}, data
    )
    out = tmp_path / "gen"
    gt = str(pair["files"][1])
    assert main(["train-generator", str(path), "--data", gt, "--out", str(out), "--quiet"]) == 0
    metrics = pd.read_csv(out / "generator_metrics.csv")
    assert (metrics["k_true"] == K_TRUE_UNKNOWN).all() and len(metrics) > 0


# --------------------------------------------------------------------------- scenario keys


def test_layout_conventions_are_the_readers_defaults() -> None:
    """A scenario naming a layout holds the conventions its reader defaults to (NGSIM:
    feet, milliseconds, lanes from the left, sEMA cleaning; PeMS: lanes from the left)."""
    data = build_data(
        {"trajectories": {"layout": "ngsim"}, "stations": {"layout": "pems"}}, "s.toml"
    )
    for f in dataclasses.fields(TrajectoryConventions):
        assert getattr(data.trajectories, f.name) == getattr(NGSIM_MAPPING, f.name), f.name
    for f in dataclasses.fields(StationConventions):
        assert getattr(data.stations, f.name) == getattr(PEMS_MAPPING, f.name), f.name
    assert data.cleaning == NGSIM_CLEANING != CleaningConfig()
    assert NGSIM_MAPPING.length_unit == "ft" and PEMS_MAPPING.lane_numbering == "left"


def test_files_scenario_holds_the_layouts_conventions(pair: dict) -> None:
    sc, _ = pair["files"]
    tr = sc.data.trajectories
    assert (tr.length_unit, tr.speed_unit, tr.time_unit, tr.lane_numbering, tr.first_lane) == (
        "ft",
        "ft/s",
        "ms",
        "left",
        1,
    )
    assert sc.data.cleaning.smoother == "ema"
    assert sc.data.stations.lane_numbering == "left" and len(sc.data.stations.stations) > 1


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (lambda d: d["trajectories"].update(units="ft"), "unknown key [data.trajectories] 'units'"),
        (lambda d: d.update(source="field"), "data.source = 'field' is not accepted"),
        (lambda d: d["trajectories"].update(layout="ngsim2"), "data.trajectories.layout"),
        (lambda d: d["trajectories"].update(speed_unit="kmh"), "data.trajectories.speed_unit"),
        (
            lambda d: d["stations"]["stations"][0].update(arc_m="x"),
            "data.stations.stations[0].arc_m",
        ),
        (lambda d: d["stations"]["stations"][0].pop("id"), "data.stations.stations[0].id"),
        (lambda d: d["stations"].update(files=d["stations"]["files"][:1]), "the same number"),
        (lambda d: d["trajectories"].update(files=["nowhere.csv"]), "does not exist"),
        (lambda d: d["trajectories"].update(files=[]), "data.trajectories.files is empty"),
    ],
)
def test_bad_data_keys_are_one_line_errors(pair: dict, tmp_path: Path, edit, needle: str) -> None:
    data = json.loads(json.dumps(pair["data"]))
    edit(data)
    path = write_files_scenario(tmp_path, pair["base"], data)
    with pytest.raises(UserError) as exc:
        load_scenario(path)
    msg = str(exc.value)
    assert needle in msg and "\n" not in msg and str(path) in msg, msg


def test_true_hidden_count_is_refused_with_files(pair: dict, tmp_path: Path) -> None:
    path = write_files_scenario(
        tmp_path, {**pair["base"], "generator": {"k_source": "truth"}}, pair["data"]
    )
    with pytest.raises(UserError, match="k_source = 'truth' needs a simulated ground truth"):
        load_scenario(path)


# --------------------------------------------------------------------------- pieces


def test_step_grid_keeps_samples_on_it_and_bridges_no_gap() -> None:
    t = np.round(np.arange(0.0, 3.01, 0.1), 6)
    t = t[(t < 1.0) | (t > 2.0)]  # a 1 s gap: no grid time inside it
    frame = pd.DataFrame(
        {
            "run": 0,
            "time_s": t,
            "vehicle_id": "a",
            "vtype": "car",
            "observed": True,
            "lane_index": 0,
            "edge_index": 0,
            "arc_m": 10.0 * t,
            "speed_mps": 10.0,
            "accel_mps2": 0.0,
        }
    )

    class Straight:  # what on_step_grid asks of a section on an open road
        closed = False

        @staticmethod
        def edge_index(arc: np.ndarray) -> np.ndarray:
            return np.zeros(len(arc), dtype=np.int64)

        @staticmethod
        def wrap(arc: np.ndarray) -> np.ndarray:
            return arc

    out = on_step_grid(frame, Straight(), 0.5, 3.0)  # type: ignore[arg-type]
    np.testing.assert_allclose(out["time_s"], [0.0, 0.5, 2.5, 3.0])
    np.testing.assert_allclose(out["arc_m"], 10.0 * out["time_s"])


def test_cross_section_rows_spread_over_the_lanes(pair: dict) -> None:
    _, gt = pair["sim"]
    section = Section.read(gt / "section.json")
    det = pd.read_csv(gt / "detectors.csv", dtype={"detector_id": str})
    det = det[(det["run"] == 0) & (det["begin_s"] == det["begin_s"].max())]
    # One station's lanes summed into a total row, as a PeMS file without lane columns.
    arc = det["arc_m"].iloc[0]
    one = det[det["arc_m"] == arc]
    total = one.iloc[:1].assign(
        lane_index=-1,
        n_veh=one["n_veh"].sum(),
        flow_vph=one["flow_vph"].sum(),
        density_vpkm=one["density_vpkm"].sum(),
        speed_mps=float(np.average(one["speed_mps"].fillna(0), weights=one["n_veh"] + 1e-12)),
    )
    spread = spread_cross_sections(total, section)
    lanes = int(section.n_lanes[section.edge_index(np.array([arc]))[0]])
    assert sorted(spread["lane_index"]) == list(range(lanes))
    assert spread["flow_vph"].sum() == pytest.approx(one["flow_vph"].sum())
    k = spread.assign(k_point_vpkm=spread["density_vpkm"])
    assert float(station_density(k, section).iloc[0]) == pytest.approx(
        one["density_vpkm"].sum(), rel=1e-9
    )


# --------------------------------------------------------------------------- CLI


def test_broken_file_exits_2_naming_file_row_and_column(
    pair: dict, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    data = json.loads(json.dumps(pair["data"]))
    broken = tmp_path / "ngsim_broken.csv"
    df = pd.read_csv(data["trajectories"]["files"][0])
    df["Local_Y"] = df["Local_Y"].astype(object)
    df.loc[4, "Local_Y"] = "n/a"
    df.to_csv(broken, index=False)
    data["trajectories"]["files"][0] = str(broken)
    path = write_files_scenario(tmp_path, pair["base"], data)
    out = tmp_path / "out"
    assert main(["simulate", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err, err
    assert str(broken) in err and "row 5" in err and "'Local_Y'" in err, err
    assert not out.exists()


def test_measured_leaders_give_the_true_pairs_and_idm(pair: dict) -> None:
    """Micro pairs from files take the leader each observed vehicle measured (NGSIM
    Preceding / Space_Headway, exported from the true leader, hidden or not, with the radar
    noise): row by row its spacing is the simulated truth's within that noise, the pairs'
    spacings and speed differences are the truth's, and the IDM fitted to them predicts
    the truth's fit on the truth's pairs within IDM_PRED_TOL. The next observed vehicle as
    the leader (the same files without those columns) is another scene."""
    (sa, ga), (sb, gb) = pair["sim"], pair["files"]
    ta, tb = load_section_truth(ga, sa), load_section_truth(gb, sb)
    manifest = json.loads((gb / "manifest.json").read_text())["field_data"]
    assert manifest["leader_rows_unmeasured"] == 0 and manifest["leader_rows_measured"] > 0
    assert "Warning" not in (gb / "data_report.md").read_text()
    # Row by row against the true leader (the files number every vehicle of a run).
    truth = pd.concat(
        [observed_rows(ga, int(run))[1] for run in ta.runs], ignore_index=True
    ).assign(vehicle_id=lambda d: d["number"].astype(str))
    both = tb.trajectories.merge(truth, on=["run", "time_s", "vehicle_id"], suffixes=("", "_t"))
    assert len(both) == len(tb.trajectories) == len(truth)
    ahead = both["leader_number"].to_numpy() > 0
    np.testing.assert_array_equal(both["leader_spacing_m"].notna(), ahead)
    d_space = (both["leader_spacing_m"] - both["spacing_m"])[ahead]
    assert d_space.std() == pytest.approx(RADAR_NOISE_M, abs=0.03) and abs(d_space.mean()) < 0.03
    d_speed = (both["leader_speed_mps"] - both["leader_speed_mps_t"])[ahead]
    assert np.sqrt((d_speed**2).mean()) < LEADER_SPEED_RMSE
    # The pairs: as many, the same spacings and speed differences as the truth's.
    oa, aa = micro_pairs(sa, ta, ta.runs, max_pairs=10**9)
    ob, ab = micro_pairs(sb, tb, tb.runs, max_pairs=10**9)
    blind = dataclasses.replace(tb, trajectories=tb.trajectories.drop(columns=list(LEADER_COLUMNS)))
    oc, _ = micro_pairs(sb, blind, tb.runs, max_pairs=10**9)
    assert len(oa) == len(ob) == len(oc)
    assert ob[:, 2].mean() == pytest.approx(oa[:, 2].mean(), rel=PAIRS_SPACING_TOL)
    assert np.abs(ob[:, 3]).mean() == pytest.approx(np.abs(oa[:, 3]).mean(), rel=0.05)
    assert oc[:, 2].mean() > 1.5 * oa[:, 2].mean()  # hidden vehicles between: far "leaders"
    veh = float(ta.vtypes["length_m"].median())
    pa, _ = calibrate_idm(oa, aa, veh)
    pb, _ = calibrate_idm(ob, ab, veh)
    diff = idm_policy_accel(oa, pb, veh) - idm_policy_accel(oa, pa, veh)
    assert np.sqrt(np.mean(diff**2)) < IDM_PRED_TOL

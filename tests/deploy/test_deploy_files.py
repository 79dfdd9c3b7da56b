"""Deployment on field data (``[data] source = "files"``): loops at the stations, the
scenario's route files or a demand sampled from the station counts by SUMO's routeSampler,
and the comparison with the stations (deploy.field, deploy.compare, sumo.route_sampler).

Tolerances:
- the oracle on the scenario's own routes is the SUMO run the field files were exported
  from (same demand, same seed): every station interval's GEH < 5 with mean GEH < 0.1
  (counts equal; the files round speeds to 0.1 mph) and the speed RMSE < 0.05 m/s;
- a demand sampled from the station counts: routeSampler's vehicle count lies within the
  range of the counted edges' counts, and the deployment's counts over the
  compared window match the stations' within 15 % on average over the stations (~50
  departures drawn uniformly in time: a 2-minute window holds its share only up to
  binomial noise, ~12 % here).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT, dump_toml

from macromicro_sumo.cli import main
from macromicro_sumo.deploy.compare import REFERENCE_FIELD, compare_folders
from macromicro_sumo.deploy.field import check_station_grid, edge_counts, station_loops
from macromicro_sumo.deploy.population import SAFETY_COLUMNS
from macromicro_sumo.deploy.run import Drive, load_context, run_method, write_method
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.netgen import random_corridor
from macromicro_sumo.sumo.route_sampler import candidate_routes
from macromicro_sumo.truth.files import data_toml, export_field_files

COUNT_TOL = 0.15  # mean over stations of the relative count error in the compared window
BREMEN = ROOT / "sumo_nets" / "highway_bremen"
BREMEN_SECTION = ["145354574", "189597495", "E0", "191842213"]


def _scenario(folder: Path, edges: list[str], network: dict, data: dict | None = None) -> Path:
    base = {
        "name": "corridor",
        "seed": 5,
        "network": {"kind": "sumo", **network},
        "section": {"edges": edges},
        "instrumented": {"penetration": 0.3},
        "simulation": {"warmup_s": 90.0, "duration_s": 120.0, "n_runs": 2},
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 200.0},
        "generator": {"held_out_fraction": 0.5},
    }
    path = folder / ("files.toml" if data else "sim.toml")
    path.write_text(dump_toml(base) + ("\n" + data_toml(data) if data else ""))
    return path


@pytest.fixture(scope="module")
def field(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A corridor simulated twice (2 runs), exported as NGSIM + PeMS files, read back as a
    files-sourced truth: once with the corridor's route files, once with the net alone."""
    folder = tmp_path_factory.mktemp("deploy_files")
    cor = random_corridor(folder / "net", 3)
    sim = folder / "gt_sim"
    edges = list(cor.section_edges)
    path = _scenario(folder, edges, {"sumocfg": str(cor.sumocfg)})
    assert main(["simulate", str(path), "--out", str(sim), "--quiet"]) == 0
    data = export_field_files(sim, folder / "field", noise_m=0.3, seed=0)
    for kind in ("trajectories", "stations"):
        data[kind]["files"] = [str(folder / "field" / f) for f in data[kind]["files"]]
    out = {}
    for name, network in (
        ("routes", {"sumocfg": str(cor.sumocfg)}),
        ("counts", {"net_file": str(cor.net_file)}),
    ):
        sub = folder / name
        sub.mkdir()
        path = _scenario(sub, edges, network, data)
        gt = sub / "gt"
        assert main(["simulate", str(path), "--out", str(gt), "--quiet"]) == 0
        out[name] = (load_scenario(path), gt)
    return out


def _deploy_oracle(sc, gt: Path, folder: Path) -> tuple[pd.DataFrame, dict]:
    ctx = load_context(sc, gt)
    res = run_method(ctx, Drive(), folder)
    write_method(ctx, res, folder, {"method": "oracle"})
    _, summary = compare_folders(gt, {"oracle": folder})
    return summary.iloc[0], json.loads((folder / "manifest.json").read_text())


def test_oracle_on_the_route_files_reproduces_the_field_stations(field, tmp_path):
    sc, gt = field["routes"]
    row, manifest = _deploy_oracle(sc, gt, tmp_path / "oracle")
    assert manifest["demand"]["source"] == "route files"
    # The manifest totals every safety column of runs.csv, the floor's raises included.
    runs = pd.read_csv(tmp_path / "oracle" / "runs.csv")
    assert {c: manifest[c] for c in SAFETY_COLUMNS} == {
        c: int(runs[c].sum()) for c in SAFETY_COLUMNS
    }
    assert row["reference"] == REFERENCE_FIELD
    # The field files are this very SUMO run (same demand and seed) read back.
    assert row["station_intervals"] >= 4 * 3  # 4 intervals after the warm-up, >= 3 stations
    assert row["share_geh_below_5"] == 1.0 and row["mean_geh"] < 0.1
    assert row["speed_rmse_mps"] < 0.05
    # Micro: against the observed vehicles; whoever drove between them is unknown.
    assert np.isfinite(row["w1_speed_mps"]) and np.isnan(row["w1_headway_s"])


def test_a_demand_sampled_from_the_station_counts(field, tmp_path):
    sc, gt = field["counts"]
    folder = tmp_path / "oracle"
    row, manifest = _deploy_oracle(sc, gt, folder)
    assert manifest["demand"]["source"].startswith("routeSampler")
    assert manifest["demand"]["window_s"] == [90.0, 210.0]
    held = int(pd.read_csv(folder / "runs.csv")["run"].iloc[0])
    assert (folder / "sumo" / f"sampled_run{held}.rou.xml").is_file()
    # routeSampler compromised between the counts: the stations of one window count
    # different vehicles (travel times, ~30 each), while on this corridor every vehicle
    # passes every edge; its demand lies within their range.
    counts = ET.parse(folder / "sumo" / f"counts_run{held}.xml").getroot()
    wanted = {e.get("id"): int(e.get("entered")) for e in counts.iter("edge")}
    routes = [v.find("route").get("edges").split() for v in ET.parse(
        folder / "sumo" / f"sampled_run{held}.rou.xml").getroot().iter("vehicle")]  # fmt: skip
    assert all(r == routes[0] for r in routes)
    assert min(wanted.values()) <= len(routes) <= max(wanted.values()), (len(routes), wanted)
    comparison, _ = compare_folders(gt, {"oracle": folder})
    whole = comparison[comparison["lane"] == -1]
    per_station = whole.groupby("station")[["flow_truth_vph", "flow_method_vph"]].sum()
    rel = per_station["flow_method_vph"] / per_station["flow_truth_vph"] - 1.0
    # One draw of ~50 departures: each station's window holds a binomial share of them
    # (~12 % standard deviation here), the same vehicles at every station.
    assert len(per_station) >= 3 and abs(rel.mean()) < COUNT_TOL, rel
    # Only the compared window: no interval of the warm-up.
    assert whole["begin_s"].min() >= 90.0
    assert row["collisions"] == 0


def test_candidate_routes_enter_by_the_on_ramp():
    routes = candidate_routes(BREMEN / "highway.net.xml", BREMEN_SECTION)
    assert BREMEN_SECTION in routes  # the main line
    ramp = [r for r in routes if r[0] not in BREMEN_SECTION]
    # The on-ramp merges onto E0: its route drives E0 and the rest of the section.
    assert len(ramp) == 1 and ramp[0][-2:] == ["E0", "191842213"]
    assert "201283198.145.16" in ramp[0]


def test_edge_counts_hold_the_window_rate_from_t0(field):
    _, gt = field["routes"]
    section = Section.read(gt / "section.json")
    det = pd.read_csv(gt / "detectors.csv", dtype={"detector_id": str})
    det = det[det["run"] == 0]
    counts = edge_counts(det, section, 90.0, 210.0)
    w = det[(det["begin_s"] >= 90.0) & (det["end_s"] <= 210.0)]
    per_station = w.groupby("arc_m")["n_veh"].sum()
    edge_of = section.edge_index(per_station.index.to_numpy())
    first = per_station[edge_of == 0].mean()  # the first edge's stations, averaged
    edge = section.edge_ids[0]
    # 120 s counted, held over the 210 s of the run.
    assert counts[edge] == round(first * 210.0 / 120.0)


def test_stations_off_the_loop_grid_or_off_a_lane_are_refused(field):
    _, gt = field["routes"]
    section = Section.read(gt / "section.json")
    det = pd.read_csv(gt / "detectors.csv", dtype={"detector_id": str})
    with pytest.raises(UserError, match=r"starts at t = 7 s, off the 30 s grid"):
        check_station_grid(det.assign(begin_s=det["begin_s"] + 7.0), 30.0, "x")
    placed = station_loops(det, section, 30.0)
    assert {p.spec.id for p in placed} == set(det["detector_id"])
    bad = det.assign(lane_index=9)
    with pytest.raises(UserError, match=r"is not on a lane of an edge of the section"):
        station_loops(bad, section, 30.0)

"""``scripts/bench_signal_approaches.py``: where the hidden count's error sits on a signalised
section's interval record (each approach's constant against the true one, the spread the
true constant leaves, each part's error)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
from conftest import ROOT
from test_hidden_count_queues import arterial_scenario

from macromicro_sumo.cli import main

sys.path.insert(0, str(ROOT / "scripts"))


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_approaches_and_parts_of_a_signalised_record(tmp_path: Path) -> None:
    """The tests' 3-signal arterial from 0 s: every approach of every run has a row; the
    record starts on an empty road, so the bound count >= 0 at the first bound gives the
    true constant within 1.5 vehicles; the true constant leaves at most the approach's own
    error (the median minimises the absolute error; clamping at 0 aside); the parts' errors
    add up to the bench's ``intervals`` error within rounding (0.5 vehicle)."""
    gt, toml = tmp_path / "gt", arterial_scenario(tmp_path)
    (tmp_path / "scenario.toml").write_text(toml.read_text())  # where the bench reads it
    assert main(["simulate", str(toml), "--out", str(gt), "--quiet"]) == 0
    script, bench = _load("bench_signal_approaches"), _load("bench_hidden_count")
    rows, parts = script.approach_rows(gt)
    assert len(rows) >= 2 and rows["entry"].iloc[0]
    assert set(rows["run"]) == set(parts["run"])
    assert (rows.groupby("run").size() == rows.groupby("run").size().iloc[0]).all()
    assert (rows["empty"].abs() <= 1.5).all(), rows[["empty", "true_constant"]]
    assert (rows["spread"] <= rows["error"] + 0.1).all(), rows[["spread", "error"]]
    assert (rows["true_vehicles"] <= rows["room"]).all()
    k = bench.errors(gt).set_index(["run", "time_s"])["intervals"]
    total = parts.set_index(["run", "time_s"])[["approaches", "exit", "rest"]].fillna(0.0)
    both = total.sum(axis=1).to_frame("parts").join(k, how="inner").dropna()
    assert len(both) >= 20
    assert np.abs(both["parts"] - both["intervals"]).max() <= 0.5 + 1e-9
    table = script.part_summary(parts)
    assert {"approaches abs", "rest abs", "all abs"} <= set(table.columns)
    cong = both.join(parts.set_index(["run", "time_s"])[["congested", "lanes"]])
    cong = cong[cong["congested"]]
    k_per_lane = float((cong["intervals"].abs() / cong["lanes"]).mean())
    assert abs(float(table.loc[True, "all abs"]) - k_per_lane) <= 0.5 / cong["lanes"].iloc[0]
    # --junction-counts: the junction stretches' errors beside the parts, which stay as they
    # were; counted from the stop bars they are nearer the truth than the rest's density.
    _, parts_j = script.approach_rows(gt, junctions=True)
    cols = ["approaches", "exit", "rest"]
    assert parts_j[cols].equals(parts[cols])
    table_j = script.part_summary(parts_j)
    assert table_j["all abs"].equals(table["all abs"])
    assert (table_j["junctions abs"] < table_j["junction_density abs"]).all(), table_j
    # --levels: the rest split where it lies; those parts add up to the rest, each part's
    # level is one value per interval, and the parts' errors stay as they were.
    _, parts_l = script.approach_rows(gt, levels=True)
    assert parts_l[cols].equals(parts[cols])
    ok = parts_l[np.isfinite(parts_l["rest"])]
    split = ok[list(script.REST_PARTS)].sum(axis=1)
    assert len(ok) >= 20 and np.allclose(split, ok["rest"], atol=1e-6)
    assert (ok["junctions"] != 0).any() and (ok["up_end"] != 0).any()
    begins = np.searchsorted(np.arange(0.0, 1e4, 90.0), ok["time_s"], "right")
    for name in ("approaches", "junctions"):
        assert (ok.groupby(["run", begins])[f"{name}_level"].nunique() == 1).all()
        shape = ok[name] - ok[f"{name}_level"]
        assert np.abs(shape.groupby([ok["run"], begins]).mean()).max() <= 1e-6
    levels = script.level_summary(parts_l)
    assert "all" in levels.index.get_level_values(0) and "junctions shape" in levels
    # --stations: every station of every interval, banded by its distance to the next stop
    # line; the point loops at the stop bars read fewer vehicles than stand there (a queue's
    # standing time is not in flow over the passing speed; docs/sections-log.md, stop 45).
    stations = script.station_rows(gt)
    per = stations.groupby(["run", "begin_s"]).size()
    assert len(per) >= 4 and (per == per.iloc[0]).all()
    assert (stations["true_vpkm"] >= 0).all() and np.isinf(stations["to_line_m"]).any()
    summary = script.station_summary(stations)
    bar = summary.loc["stop bar"]
    assert (bar["est_vpkm"] < bar["true_vpkm"]).all(), summary
    assert summary["intervals"].sum() == len(stations)
    # Where each loop falls in SUMO's standing lattice (fronts 1 m + n x 7.5 m before the
    # line): the stop bar (0.5 m) stands in front of the first car, so "in a gap"; the
    # stations past the last line are "past the last line"; one place per station.
    assert set(bar.index) == {"in a gap"}, summary
    past = stations[np.isinf(stations["to_line_m"])]
    assert (past["standing"] == "past the last line").all() and len(past)
    assert (stations.groupby(["run", "arc_m"])["standing"].nunique() == 1).all()


def test_a_runs_ground_truth_names_its_scenario(tmp_path: Path) -> None:
    """A run's ``ground_truth`` has no scenario beside it: the run's manifest names it; a
    ground truth simulated on its own, its own manifest."""
    script = _load("bench_signal_approaches")
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "scenario.toml").write_text("")
    assert script.scenario_file(tmp_path / "gt" / "x") == tmp_path / "gt" / "scenario.toml"
    run = tmp_path / "run"
    (run / "ground_truth").mkdir(parents=True)
    (run / "manifest.json").write_text('{"scenario_file": "/elsewhere/k528.toml"}')
    assert script.scenario_file(run / "ground_truth") == Path("/elsewhere/k528.toml")
    # ``simulate SCENARIO --out GT`` anywhere: the ground truth's own manifest names it.
    alone = tmp_path / "s1161" / "gt"
    alone.mkdir(parents=True)
    (alone / "manifest.json").write_text('{"scenario_file": "/elsewhere/k1161.toml"}')
    assert script.scenario_file(alone) == Path("/elsewhere/k1161.toml")
    # Tables name the net: the run's folder, else the bench's arterial above its variant.
    assert script.truth_name(run / "ground_truth") == "run"
    bench = tmp_path / "arterial_801" / "boundary_stations"
    assert script.truth_name(bench / "gt") == "arterial_801"
    assert script.truth_name(bench / "occupancy_loop_2m" / "gt") == "arterial_801"
    assert script.truth_name(tmp_path / "x" / "y" / "gt") == "x"

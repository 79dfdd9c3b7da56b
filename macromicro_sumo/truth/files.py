"""A ground-truth folder from field files (``[data] source = "files"``), not from SUMO.

The observed vehicles' trajectories and the stations' intervals are read by ``fielddata``
(one file of each per run: a recording), cleaned, and written into the same folder
``macromicro simulate`` writes (docs/sections.md), so the generator and policy stages run
on it unchanged. What field data cannot give is marked, not invented:

- trajectories hold only the observed vehicles; every row has ``observed`` True;
- ``k_true`` is unknown: -1 in ``k_estimate.csv`` (as ``k_est_flow_speed``'s -1), with
  ``k_error`` 0; the loader wants finite numbers there (``truth.section.K_COLUMNS``);
- no per-vehicle passages: ``std_spacing_m`` is NaN (psi's spread term is then off); the
  speed bounds of an interval are the observed vehicles' extremes in it (the stations
  give means only; ``data.section.psi_table`` widens them by 10 %);
- station rows over the whole cross-section (``lane_index`` -1, PeMS totals) are spread
  over the section's lanes at the station, so each station's density counts once.

Times are put on the scenario's step grid (``simulation.step_length_s``: the policy's dt):
samples already on it are kept as they are, others are interpolated between the samples
around them, never across a gap (``cleaning.gap_factor``).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.fielddata.cleaning import (
    CleanStations,
    CleanTrajectories,
    clean_stations,
    clean_trajectories,
)
from macromicro_sumo.fielddata.export import export_ngsim, export_pems
from macromicro_sumo.fielddata.mapping import (
    StationMapping,
    TrajectoryMapping,
    lanes_at,
    station_mapping,
    trajectory_mapping,
)
from macromicro_sumo.fielddata.report import leader_counts, write_data_report
from macromicro_sumo.fielddata.stations import (
    Stations,
    read_generic_stations,
    read_pems,
    read_sumo_detectors,
)
from macromicro_sumo.fielddata.trajectories import (
    Trajectories,
    read_fcd,
    read_generic_trajectories,
    read_highd,
    read_ngsim,
)
from macromicro_sumo.files import prepare_out_dir, staging_dir, write_csv, write_manifest
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.section import Section, read_section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import read_net, scenario_inputs
from macromicro_sumo.truth.density import DEFAULT_VEHICLE_LENGTH_M
from macromicro_sumo.truth.hidden_count import k_estimates
from macromicro_sumo.truth.interval_counts import interval_record
from macromicro_sumo.truth.section_macro import detector_macro

K_TRUE_UNKNOWN = -1
"""``k_true`` of a field-data snapshot: nobody counted the hidden vehicles."""
PASSAGE_COLUMNS = ("run", "detector_id", "time_s", "speed_mps", "length_m")


# --------------------------------------------------------------------------- reading


def _mapping_table(cfg: Any, cls: type, run: int) -> dict[str, Any]:
    """The keys of ``cls`` (a fielddata mapping) out of a scenario table, with the run."""
    names = {f.name for f in dataclasses.fields(cls)}
    table = {k: v for k, v in dataclasses.asdict(cfg).items() if k in names}
    return table | {"run": run}


def read_trajectory_file(
    sc: SectionScenario, section: Section, path: Path, run: int
) -> Trajectories:
    """One trajectory file of ``[data.trajectories]`` as run ``run``."""
    cfg = sc.data.trajectories
    m = trajectory_mapping(_mapping_table(cfg, TrajectoryMapping, run), sc.source)
    if cfg.layout == "ngsim":
        return read_ngsim(path, section, m, cfg.outside)
    if cfg.layout == "highd":
        return read_highd(path, section, m, cfg.outside)
    if cfg.layout == "fcd":
        return read_fcd(path, section, m, cfg.outside)
    return read_generic_trajectories(path, section, m, cfg.columns, cfg.outside)


def read_station_file(sc: SectionScenario, section: Section, path: Path, run: int) -> Stations:
    """One station file of ``[data.stations]`` as run ``run``."""
    cfg = sc.data.stations
    table = _mapping_table(cfg, StationMapping, run)
    table["stations"] = [dataclasses.asdict(p) for p in cfg.stations]
    m = station_mapping(table, sc.source)
    if cfg.layout == "sumo":
        adds = cfg.additional
        return read_sumo_detectors(path, section, sc.resolve(adds[run % len(adds)]), m)
    if cfg.layout == "pems":
        return read_pems(path, section, m)
    return read_generic_stations(path, section, m, cfg.columns)


# --------------------------------------------------------------------------- shaping


def on_step_grid(
    frame: pd.DataFrame, section: Section, dt: float, gap_factor: float
) -> pd.DataFrame:
    """Each vehicle's rows at the multiples of ``dt`` within its samples: a sample on the
    grid as it is; between samples, arc, speed and acceleration interpolated linearly and
    the lane of the sample before; no grid time inside a gap (a step longer than
    ``gap_factor`` of the vehicle's median sampling step and longer than ``dt``)."""
    out = []
    for _, g in frame.groupby(["run", "vehicle_id"], sort=False):
        g = g.sort_values("time_s", kind="stable")
        t = g["time_s"].to_numpy(dtype=float)
        k = np.arange(np.ceil(t[0] / dt - 1e-6), np.floor(t[-1] / dt + 1e-6) + 1)
        grid = np.round(k * dt, 6)
        if grid.size == 0:
            continue
        step = np.diff(t)
        gap_s = max(gap_factor * float(np.median(step)), dt) if step.size else dt
        left = np.clip(np.searchsorted(t, grid + 1e-6, side="right") - 1, 0, len(t) - 1)
        right = np.minimum(left + 1, len(t) - 1)
        exact = np.abs(t[left] - grid) < 1e-6
        keep = exact | (t[right] - t[left] <= gap_s + 1e-9)
        grid, left = grid[keep], left[keep]
        arc = g["arc_m"].to_numpy(dtype=float)
        if section.closed:  # a loop: interpolate the unwrapped arc
            arc = np.unwrap(arc, period=section.length_m)
        a = section.wrap(np.interp(grid, t, arc))
        lead = grid_leaders(g, t, grid, left) if "leader_spacing_m" in g.columns else {}
        out.append(
            pd.DataFrame(
                {
                    "run": g["run"].iloc[0],
                    "time_s": grid,
                    "vehicle_id": g["vehicle_id"].iloc[0],
                    "vtype": g["vtype"].iloc[0],
                    "observed": True,
                    "lane_index": g["lane_index"].to_numpy()[left],
                    "edge_index": section.edge_index(a).astype(np.int64),
                    "arc_m": a,
                    "speed_mps": np.interp(grid, t, g["speed_mps"].to_numpy(dtype=float)),
                    "accel_mps2": np.interp(grid, t, g["accel_mps2"].to_numpy(dtype=float)),
                }
                | lead
            )
        )
    if not out:
        return frame.iloc[:0]
    df = pd.concat(out, ignore_index=True)
    return df.sort_values(["run", "time_s", "lane_index", "arc_m"], kind="stable").reset_index(
        drop=True
    )


def grid_leaders(
    g: pd.DataFrame, t: np.ndarray, grid: np.ndarray, left: np.ndarray
) -> dict[str, np.ndarray]:
    """A vehicle's measured leader at the grid times: spacing and leader speed interpolated
    between two samples behind the same leader, else the sample before's (a new leader is
    a jump, not a slope)."""
    ids = g["leader_id"].fillna("").astype(str).to_numpy()
    right = np.minimum(left + 1, len(t) - 1)
    same = ids[left] == ids[right]
    out: dict[str, np.ndarray] = {"leader_id": ids[left]}
    for col in ("leader_spacing_m", "leader_speed_mps"):
        x = g[col].to_numpy(dtype=float)
        w = np.clip((grid - t[left]) / np.maximum(t[right] - t[left], 1e-9), 0.0, 1.0)
        out[col] = np.where(same, x[left] + w * (x[right] - x[left]), x[left])
    return out


def spread_cross_sections(det: pd.DataFrame, section: Section) -> pd.DataFrame:
    """Rows of a station's whole cross-section (``lane_index`` -1) as one row per lane of
    the section there: counts, flows and densities divided by the lanes, speed and
    occupancy (PeMS: the mean over lanes) kept. The K estimate takes a station's density
    as the mean over its lanes' rows times its lanes; a total row would count n times."""
    whole = det["lane_index"].to_numpy() < 0
    if not whole.any():
        return det
    rows = det[whole]
    n = lanes_at(section, rows["arc_m"].to_numpy(dtype=float)).astype(np.int64)
    rep = rows.loc[rows.index.repeat(n)].copy()
    per = np.repeat(n, n).astype(float)
    rep["lane_index"] = np.concatenate([np.arange(k) for k in n])
    for col in ("n_veh", "flow_vph", "density_vpkm"):
        rep[col] = rep[col].to_numpy(dtype=float) / per
    out = pd.concat([det[~whole], rep], ignore_index=True)
    return out.sort_values(["run", "begin_s", "arc_m", "lane_index"], kind="stable").reset_index(
        drop=True
    )


def lane_detector_ids(det: pd.DataFrame) -> pd.Series:
    """``detector_id`` of every row, one per loop as in a simulated ground truth: a station
    id shared by several lanes (PeMS, spread cross-sections) gets ``_l<lane index>``, so a
    deployment's loops can carry the same ids (``deploy.calibrate`` matches on them)."""
    ids = det["detector_id"].astype(str)
    shared = det.groupby(ids)["lane_index"].transform("nunique") > 1
    return ids.where(~shared, ids + "_l" + det["lane_index"].astype(str))


def vtype_table(trajs: list[Trajectories], traj: pd.DataFrame, min_gap_m: float) -> pd.DataFrame:
    """vtypes.csv of field data: each vtype's median vehicle length in the files (SUMO's
    passenger car where the files give none); the car-following model is unknown."""
    veh = pd.concat([t.vehicles for t in trajs], ignore_index=True)
    rows = []
    for vtype, g in veh.groupby("vtype", sort=True):
        length = float(np.nanmedian(g["length_m"])) if g["length_m"].notna().any() else np.nan
        rows.append(
            {
                "vtype": str(vtype),
                "car_follow_model": "unknown",
                "vclass": "passenger",
                "length_m": length if np.isfinite(length) else DEFAULT_VEHICLE_LENGTH_M,
                "min_gap_m": min_gap_m,
                "vehicles": int(traj.loc[traj["vtype"] == vtype, "vehicle_id"].nunique()),
            }
        )
    return pd.DataFrame(rows)


def observed_speed_bounds(macro: pd.DataFrame, traj: pd.DataFrame) -> pd.DataFrame:
    """Each interval's speed bounds from the observed vehicles in it (the stations give
    means only); NaN where none drove (psi then falls back to [0, limit])."""
    lo, hi = np.full(len(macro), np.nan), np.full(len(macro), np.nan)
    for i, r in enumerate(macro.itertuples(index=False)):
        v = traj.loc[
            (traj["run"] == r.run) & (traj["time_s"] >= r.begin_s) & (traj["time_s"] < r.end_s),
            "speed_mps",
        ].to_numpy()
        if v.size:
            lo[i], hi[i] = v.min(), v.max()
    return macro.assign(speed_min_mps=lo, speed_max_mps=hi)


def read_field_data(
    sc: SectionScenario, section: Section, progress: bool = True
) -> tuple[list[CleanTrajectories], list[CleanStations]]:
    """Every file of ``[data]`` read and cleaned; file i of each kind is run i."""
    cleaning = sc.data.cleaning  # the scenario's table is the cleaning's own config class
    trajs, stations = [], []
    pairs = list(zip(sc.data.trajectories.files, sc.data.stations.files, strict=True))
    for run, (tf, sf) in enumerate(
        tqdm(pairs, desc="read files", unit="run", disable=not progress)
    ):
        trajs.append(
            clean_trajectories(read_trajectory_file(sc, section, sc.resolve(tf), run), cleaning)
        )
        stations.append(
            clean_stations(read_station_file(sc, section, sc.resolve(sf), run), cleaning)
        )
    return trajs, stations


# --------------------------------------------------------------------------- the stage


def truth_from_files(
    sc: SectionScenario, out: Path | str, command: str = "", progress: bool = True
) -> Path:
    """The ground-truth folder of ``macromicro simulate`` from ``[data]``'s files."""
    inputs = scenario_inputs(sc)
    section = read_section(inputs.net_file, list(sc.section.edges), sc.section.closed, sc.source)
    t_start = time.perf_counter()
    trajs, stations = read_field_data(sc, section, progress)
    dt = sc.simulation.step_length_s
    files = sc.data.trajectories.files
    frames = [on_step_grid(c.frame, section, dt, sc.data.cleaning.gap_factor) for c in trajs]
    for f, c in zip(frames, trajs, strict=True):
        if f.empty:
            raise UserError(
                f"{c.source.file}: no vehicle is recorded at a multiple of "
                f"simulation.step_length_s = {dt:g} s (the grid the policy steps on)"
            )
    traj = pd.concat(frames, ignore_index=True)
    det = pd.concat([c.frame for c in stations], ignore_index=True)
    for c in stations:
        if c.frame.empty:
            raise UserError(f"{c.source.file}: every interval was excluded by the cleaning")
    det = spread_cross_sections(det, section)
    det["detector_id"] = lane_detector_ids(det)
    vt = vtype_table([c.source for c in trajs], traj, sc.bounds.min_gap_m)
    min_spacing = float(vt["length_m"].min()) + sc.bounds.min_gap_m
    passages = pd.DataFrame({c: [] for c in PASSAGE_COLUMNS})
    start = float(det["begin_s"].min())
    det_macro = observed_speed_bounds(
        detector_macro(det, passages, start, min_spacing, section), traj
    )
    # The stations' interval counts between stations where speeds collapse; at signals the
    # approaches by the net file's programs (the data's clock taken as the programs').
    record = interval_record(
        det, section, read_net(inputs.net_file), inputs.net_file, sc.detectors.near_line_queue
    )
    k_df = k_estimates(
        traj, det_macro, section, sc.generator.snapshot_every_s, sc.detectors.k_window_s, record
    )
    if k_df.empty:
        raise UserError(
            f"{sc.source}: no observed vehicle is on the section at a snapshot time (multiples "
            f"of generator.snapshot_every_s = {sc.generator.snapshot_every_s:g} s) inside a "
            "station interval; check the clocks (data.*.clock_offset_s, clock_origin)"
        )
    k_df = k_df.assign(k_true=K_TRUE_UNKNOWN, k_error=0)
    runs = pd.DataFrame(
        [
            {
                "run": run,
                "sumo_seed": sc.seed + run,  # what a deployment seeds its SUMO run with
                "vehicles_seen": int(traj.loc[traj["run"] == run, "vehicle_id"].nunique()),
                "observed": int(traj.loc[traj["run"] == run, "vehicle_id"].nunique()),
                "collisions": 0,
                "teleports": 0,
                "trajectory_file": str(sc.resolve(files[run])),
                "station_file": str(sc.resolve(sc.data.stations.files[run])),
            }
            for run in range(len(files))
        ]
    )
    out = prepare_out_dir(out)
    with staging_dir(out) as stage:
        section.write(stage / "section.json")
        write_csv(traj, stage / "trajectories.csv")
        write_csv(vt, stage / "vtypes.csv")
        write_csv(det, stage / "detectors.csv")
        write_csv(det_macro, stage / "macro.csv")
        write_csv(k_df, stage / "k_estimate.csv")
        write_csv(runs, stage / "runs.csv")
        write_data_report(stage, trajs, stations)
        manifest = build_manifest(sc, command, stage="simulate")
        manifest.update(
            data_source="files",
            section_length_m=section.length_m,
            section_lanes=section.n_lanes.tolist(),
            detectors={"source": "field", "count": int(det["detector_id"].nunique())},
            car_following_models=["unknown (field data)"],
            collisions=0,
            teleports=0,
            k_estimate={
                "snapshots": len(k_df),
                "k_true": "unknown (field data): k_true = -1, k_error = 0",
                "mean_k_est": float(k_df["k_est"].mean()),
            },
            field_data={
                "trajectory_rows_read": int(sum(len(c.frame) for c in trajs)),
                "trajectory_rows_on_grid": len(traj),
                "dropped_off_section": int(sum(c.source.dropped_off_section for c in trajs)),
                "station_rows_kept": int(sum(len(c.frame) for c in stations)),
                "station_rows_dropped": int(sum(len(c.dropped) for c in stations)),
                # Micro pairs take the vehicles' own leader measurement where a layout has
                # one; rows without: the next observed vehicle (data_report.md warns).
                "leader_rows_measured": int(
                    sum(leader_counts(c)["leader_rows_measured"] for c in trajs)
                ),
                "leader_rows_unmeasured": int(
                    sum(leader_counts(c).get("leader_rows_unmeasured", 0) for c in trajs)
                ),
            },
            timings_s={"simulate": round(time.perf_counter() - t_start, 3)},
        )
        write_manifest(manifest, stage)
    return out


# --------------------------------------------------------------------------- fixtures


def export_field_files(
    gt: Path, folder: Path, noise_m: float = 0.3, seed: int = 0
) -> dict[str, Any]:
    """Field files of a simulated ground truth ``gt``, one pair per run: the observed
    vehicles as NGSIM (feet, lanes from the left, N(0, ``noise_m``) position noise drawn
    with ``seed`` + run) and the E1 loops as a PeMS station file. Returns the ``[data]``
    table that reads them back (file paths relative to ``folder``)."""
    folder.mkdir(parents=True, exist_ok=True)
    runs = sorted(int(r) for r in pd.read_csv(Path(gt) / "runs.csv")["run"])
    traj_files, station_files = [], []
    for run in runs:
        path = folder / f"ngsim_run{run}.csv"
        tm, _ = export_ngsim(gt, path, run, noise_m, seed + run)
        sm = export_pems(gt, folder / f"pems_run{run}.csv", run)
        traj_files.append(f"ngsim_run{run}.csv")
        station_files.append(f"pems_run{run}.csv")
    return {
        "source": "files",
        "trajectories": {
            "layout": "ngsim",
            "files": traj_files,
            # Noise carries a few positions past the end of a lane that ends (an on-ramp's
            # merge lane): dropped and counted; the step grid bridges the one-sample gaps.
            "outside": "drop",
            "clock_offset_s": tm.clock_offset_s,
        },
        "stations": {
            "layout": "pems",
            "files": station_files,
            "clock_origin": sm.clock_origin,
            "interval_s": sm.interval_s,
            "stations": [{"id": p.id, "arc_m": round(p.arc_m, 4)} for p in sm.stations],
        },
    }


def data_toml(table: dict[str, Any], prefix: str = "data") -> str:
    """A ``[data]`` table as TOML text (nested tables; lists of tables inline)."""
    lines = [f"[{prefix}]"]
    subs = []
    for key, value in table.items():
        if isinstance(value, dict):
            subs.append((key, value))
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            rows = ",\n".join(
                "    {" + ", ".join(f"{k} = {json.dumps(v)}" for k, v in d.items()) + "}"
                for d in value
            )
            lines.append(f"{key} = [\n{rows},\n]")
        else:
            lines.append(f"{key} = {json.dumps(value)}")
    text = "\n".join(lines) + "\n"
    for key, value in subs:
        text += "\n" + data_toml(value, f"{prefix}.{key}")
    return text

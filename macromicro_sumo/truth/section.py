"""Ground truth on a section of the user's network: their demand, their models, detectors.

SUMO runs the user's routes and flows with their vehicle types (whatever car-following
model they use: ``vtypes.csv`` records which). Every step, every vehicle on the section is
recorded in section coordinates (lane index, arc). Detectors are the user's own E1/E2 on
the section (re-created with our output files and interval, so nothing is written next to
the user's files) or, where there are none, E1 loops placed every ``auto_spacing_m`` on
every lane. An instantaneous loop sits beside every E1 loop: its per-vehicle passages give
the spread of the spacings, as on the ring. Instrumented vehicles are chosen by a
penetration rate, a vType or explicit IDs.
"""

from __future__ import annotations

import hashlib
import json
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import pandas as pd

from macromicro_sumo.data.macro import passage_spacings
from macromicro_sumo.data.section import SectionTruth, at_snapshot_times
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import (
    check_memory,
    check_outputs,
    prepare_out_dir,
    read_checked_csv,
    read_manifest,
    staging_dir,
    write_csv,
    write_manifest,
)
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.section import Section, lane_leaders, read_section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import (
    DetectorSpec,
    SumoInputs,
    VType,
    check_demand,
    check_vehicle_ids,
    read_net,
    resolve_inputs,
    user_detectors,
)
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.ring_detectors import (
    E1_FILE,
    E2_FILE,
    INSTANT_FILE,
    read_passages,
    records,
    speed_or_nan,
)

_DETECTOR_TAGS = {
    "inductionLoop",
    "e1Detector",
    "laneAreaDetector",
    "e2Detector",
    "instantInductionLoop",
}


def scenario_inputs(sc: SectionScenario) -> SumoInputs:
    """The user's SUMO files named by the scenario, resolved and checked to exist."""
    n = sc.network
    return resolve_inputs(
        sc.resolve(n.sumocfg) if n.sumocfg else None,
        sc.resolve(n.net_file) if n.net_file else None,
        [sc.resolve(p) for p in n.route_files],
        [sc.resolve(p) for p in n.additional_files],
        sc.source,
    )


def load_section(sc: SectionScenario) -> tuple[SumoInputs, Section, dict[str, VType]]:
    """Inputs, the section and the vehicle types, every check done before SUMO starts."""
    inputs = scenario_inputs(sc)
    net = read_net(inputs.net_file)
    vtypes = check_demand(inputs, net)
    section = read_section(inputs.net_file, list(sc.section.edges), sc.section.closed, sc.source)
    if sc.instrumented.vtype and sc.instrumented.vtype not in vtypes:
        raise UserError(
            f"{sc.source}: instrumented.vtype = {sc.instrumented.vtype!r} is not a vType of the "
            f"demand; accepted: one of {', '.join(sorted(vtypes))}"
        )
    check_vehicle_ids(inputs, sc.instrumented.ids, f"{sc.source}: instrumented.ids")
    return inputs, section, vtypes


# --------------------------------------------------------------------------- detectors


@dataclass(frozen=True)
class Placed:
    """A detector on the section: its SUMO definition and where it sits on the arc."""

    spec: DetectorSpec
    source: str  # "user" or "auto"
    lane_index: int
    arc_m: float


def place_detectors(sc: SectionScenario, inputs: SumoInputs, section: Section) -> list[Placed]:
    """The user's detectors on the section, else loops every ``auto_spacing_m`` per lane."""
    placed: list[Placed] = []
    if sc.detectors.use_user:
        net = read_net(inputs.net_file)
        for spec in user_detectors(inputs, net):
            hit = section.locate(spec.lane_id, spec.pos_m)
            if hit is not None and not spec.lane_id.startswith(":"):
                placed.append(Placed(spec, "user", hit[0], hit[1]))
    if placed:
        return placed
    step = sc.detectors.auto_spacing_m
    if step <= 0:
        raise UserError(
            f"{sc.source}: the section has no detector of the user's files and "
            "detectors.auto_spacing_m = 0 switches placement off; accepted: auto_spacing_m > 0"
        )
    period = sc.detectors.interval_s
    for arc in np.arange(step / 2, section.length_m, step):
        e = int(section.edge_index(np.array([arc]))[0])
        pos = float(arc - section.offsets_m[e])
        if pos > section.lengths_m[e] - 0.5:
            continue  # in a junction: skip this station
        for lane_id in section.edge_lane_ids[e]:
            idx = section.lanes[lane_id][1]
            spec = DetectorSpec(f"auto_{lane_id}_{arc:.0f}", "e1", lane_id, pos, 0.0, period, "")
            placed.append(Placed(spec, "auto", idx, float(arc)))
    if not placed:
        raise UserError(
            f"{sc.source}: detectors.auto_spacing_m = {step:g} places no loop on a "
            f"{section.length_m:.0f} m section; accepted: < {section.length_m:.0f}"
        )
    return placed


def detectors_xml(placed: list[Placed], interval_s: float) -> str:
    """Our definitions of the detectors (E1 + an instantaneous loop beside it, or E2)."""
    rows = ["<additional>"]
    for p in placed:
        s = p.spec
        did, lane = quoteattr(s.id), quoteattr(s.lane_id)
        if s.kind == "e1":
            rows.append(
                f'    <inductionLoop id={did} lane={lane} pos="{s.pos_m:.3f}" '
                f'period="{interval_s:g}" file="{E1_FILE}"/>'
            )
            rows.append(
                f"    <instantInductionLoop id={quoteattr('i_' + s.id)} lane={lane} "
                f'pos="{s.pos_m:.3f}" file="{INSTANT_FILE}"/>'
            )
        else:
            lanes = quoteattr(" ".join(s.lane_ids or (s.lane_id,)))
            rows.append(
                f'    <laneAreaDetector id={did} lanes={lanes} pos="{s.pos_m:.3f}" '
                f'length="{s.length_m:.3f}" period="{interval_s:g}" file="{E2_FILE}"/>'
            )
    rows.append("</additional>")
    return "\n".join(rows) + "\n"


def _without_detectors(src: Path, dst: Path) -> Path:
    """A copy of a user's additional file minus its detectors (we define our own)."""
    tree = ET.parse(src)
    root = tree.getroot()
    for parent in list(root.iter()):
        for child in list(parent):
            if child.tag.split("}")[-1] in _DETECTOR_TAGS:
                parent.remove(child)
    tree.write(dst)
    return dst


def read_detectors(
    run_dir: Path, run: int, placed: list[Placed]
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per-interval table, per-vehicle passages) of one run's detector output."""
    where = {p.spec.id: p for p in placed}
    rows = []
    for r in records(run_dir / E1_FILE, "interval", required=False):
        p = where[r["id"]]
        flow, speed = float(r["flow"]), speed_or_nan(r.get("harmonicMeanSpeed"))
        rows.append(
            {
                "run": run,
                "detector_id": r["id"],
                "kind": "e1",
                "source": p.source,
                "lane_index": p.lane_index,
                "arc_m": p.arc_m,
                "begin_s": float(r["begin"]),
                "end_s": float(r["end"]),
                "n_veh": int(r["nVehContrib"]),
                "flow_vph": flow,
                "speed_mps": speed,
                "occupancy_pct": float(r["occupancy"]),
                # Fundamental relation k = q / v (harmonic mean: the space-mean speed).
                "density_vpkm": flow / speed / 3.6 if speed > 0 else 0.0,
                "length_m": 0.0,
            }
        )
    for r in records(run_dir / E2_FILE, "interval", required=False):
        p = where[r["id"]]
        rows.append(
            {
                "run": run,
                "detector_id": r["id"],
                "kind": "e2",
                "source": p.source,
                "lane_index": p.lane_index,
                "arc_m": p.arc_m,
                "begin_s": float(r["begin"]),
                "end_s": float(r["end"]),
                "n_veh": int(r["nVehSeen"]),
                "flow_vph": np.nan,
                "speed_mps": speed_or_nan(r.get("meanSpeed")),
                "occupancy_pct": float(r["meanOccupancy"]),
                "density_vpkm": float(r["meanVehicleNumber"]) / p.spec.length_m * 1000.0,
                "length_m": p.spec.length_m,
                "sampled_seconds_s": float(r["sampledSeconds"]),
            }
        )
    det = pd.DataFrame(rows)
    passages = read_passages(run_dir / INSTANT_FILE, run, required=False)
    return det, passages


def station_cells(arcs: np.ndarray, section: Section) -> np.ndarray:
    """Arc length each detector station stands for: the section split half-way between
    stations (around the loop on a closed section)."""
    order = np.argsort(arcs)
    a = arcs[order]
    if len(a) == 1:
        cells = np.array([section.length_m])
    elif section.closed:
        gaps = np.diff(np.concatenate([a, [a[0] + section.length_m]]))
        cells = 0.5 * (gaps + np.roll(gaps, 1))
    else:
        mids = np.concatenate([[0.0], 0.5 * (a[1:] + a[:-1]), [section.length_m]])
        cells = np.diff(mids)
    out = np.empty_like(cells)
    out[order] = cells
    return out


def detector_macro(
    det: pd.DataFrame,
    passages: pd.DataFrame,
    warmup_s: float,
    min_spacing_m: float,
    section: Section,
) -> pd.DataFrame:
    """Macro statistics per run and interval as the section's detectors estimate them.

    Speed: space-mean (E2 weighted by time on the detector; E1 harmonic means weighted by
    counts). Density per lane: E2 vehicles per metre, E1 flow / speed, averaged over the
    detectors. Vehicles on the section: E1 stations' density summed over their lanes and
    integrated along the arc (each station stands for the stretch half-way to its
    neighbours: lane counts that change along the section are weighted right); E2: their
    vehicles scaled to the section's lane length. Spacing spread and speed bounds: from
    the per-vehicle passages.
    """
    spacings = passage_spacings(passages)
    stations = np.sort(det.loc[det["kind"] == "e1", "arc_m"].unique())
    cells = (
        dict(zip(stations, station_cells(stations, section), strict=True)) if len(stations) else {}
    )
    rows = []
    det = det[det["begin_s"] >= warmup_s - 1e-9]
    for (run, begin, end), g in det.groupby(["run", "begin_s", "end_s"], sort=True):
        e1, e2 = g[g["kind"] == "e1"], g[g["kind"] == "e2"]
        if len(e2):
            ss = e2["sampled_seconds_s"].to_numpy()
            v = e2["speed_mps"].to_numpy()
            speed = float(np.nansum(v * ss) / ss.sum()) if ss.sum() > 0 else np.nan
            density = float(np.average(e2["density_vpkm"], weights=e2["length_m"]))
            vehicles = density / 1000.0 * section.lane_length_m
        else:
            n, v = e1["n_veh"].to_numpy(), e1["speed_mps"].to_numpy()
            ok = n > 0
            speed = float(n[ok].sum() / (n[ok] / v[ok]).sum()) if ok.any() else np.nan
            density = float(e1["density_vpkm"].mean())
            per_station = e1.groupby("arc_m")["density_vpkm"].sum()
            vehicles = float(sum(k / 1000.0 * cells[a] for a, k in per_station.items()))
        ip = passages[
            (passages["run"] == run) & (passages["time_s"] >= begin) & (passages["time_s"] < end)
        ]
        sp = spacings[
            (spacings["run"] == run) & (spacings["time_s"] >= begin) & (spacings["time_s"] < end)
        ]
        ps = ip["speed_mps"].to_numpy()
        d = sp["spacing_m"].to_numpy()
        d = d[d >= min_spacing_m * 0.5]  # a lane change between two loops is not a spacing
        rows.append(
            {
                "run": run,
                "begin_s": begin,
                "end_s": end,
                "source": "detectors",
                "mean_speed_mps": speed,
                "std_speed_mps": float(ps.std(ddof=1)) if ps.size > 1 else np.nan,
                "density_vpkm_lane": density,
                "mean_spacing_m": 1000.0 / density if density > 0 else np.nan,
                "std_spacing_m": float(d.std(ddof=1)) if d.size > 1 else np.nan,  # sample std
                "speed_min_mps": float(ps.min()) if ps.size else np.nan,
                "speed_max_mps": float(ps.max()) if ps.size else np.nan,
                "vehicles": vehicles,
            }
        )
    return pd.DataFrame(rows)


def trajectory_macro(
    traj: pd.DataFrame, section: Section, interval_s: float, warmup_s: float, end_s: float
) -> pd.DataFrame:
    """The same statistics from the full trajectories (what the simulation knows)."""
    rows = []
    bounds = np.arange(warmup_s, end_s + 1e-9, interval_s)
    for run, g in traj.groupby("run", sort=True):
        for begin, end in zip(bounds[:-1], bounds[1:], strict=True):
            w = g[(g["time_s"] >= begin) & (g["time_s"] < end)]
            if w.empty:
                continue
            spacing = []
            for _, s in w.groupby("time_s"):
                lead, sp = lane_leaders(
                    s["lane_index"].to_numpy(),
                    s["arc_m"].to_numpy(),
                    section.length_m,
                    section.closed,
                )
                spacing.append(sp[lead >= 0])
            d = np.concatenate(spacing) if spacing else np.array([])
            n_t = w.groupby("time_s").size().mean()
            density = n_t / section.lane_length_m * 1000.0
            rows.append(
                {
                    "run": run,
                    "begin_s": begin,
                    "end_s": end,
                    "source": "trajectories",
                    "mean_speed_mps": float(w["speed_mps"].mean()),
                    "std_speed_mps": float(w["speed_mps"].std(ddof=0)),
                    "density_vpkm_lane": density,
                    "mean_spacing_m": 1000.0 / density if density > 0 else np.nan,
                    "std_spacing_m": float(d.std()) if d.size > 1 else np.nan,
                    "speed_min_mps": float(w["speed_mps"].min()),
                    "speed_max_mps": float(w["speed_mps"].max()),
                    "vehicles": float(n_t),
                }
            )
    return pd.DataFrame(rows)


def k_estimates(
    traj: pd.DataFrame,
    det_macro: pd.DataFrame,
    section: Section,
    every_s: float,
    window_s: float,
) -> pd.DataFrame:
    """Hidden count per snapshot time: the truth, and the estimate from the detectors.

    Estimate: round(vehicles on the section by the detectors) - observed vehicles, the
    detectors' count (see ``detector_macro``) averaged over the intervals centred within ``window_s``
    of the snapshot (``detectors.k_window_s``; at least the interval holding it). Longer
    windows average out platoons that one interval's loops see or miss.
    """
    rows = []
    for (run, t), g in at_snapshot_times(traj, every_s).groupby(["run", "time_s"], sort=True):
        r = det_macro[det_macro["run"] == run]
        centre = 0.5 * (r["begin_s"] + r["end_s"])
        m = r[(centre >= t - window_s / 2) & (centre <= t + window_s / 2)]
        if m.empty:
            m = r[(r["begin_s"] <= t) & (r["end_s"] > t)]
        vehicles = float(m["vehicles"].mean()) if len(m) else np.nan
        if not np.isfinite(vehicles):
            continue
        n_obs = int(g["observed"].sum())
        total = int(round(vehicles))
        k_true = len(g) - n_obs
        k_est = max(0, total - n_obs)
        rows.append(
            {
                "run": run,
                "time_s": t,
                "n_vehicles": len(g),
                "n_observed": n_obs,
                "k_true": k_true,
                "k_est": k_est,
                "k_error": k_est - k_true,
            }
        )
    return pd.DataFrame(
        rows, columns=["run", "time_s", "n_vehicles", "n_observed", "k_true", "k_est", "k_error"]
    )


# --------------------------------------------------------------------------- runs


def _is_instrumented(sc: SectionScenario, vid: str, vtype: str, run: int) -> bool:
    """Deterministic per (seed, run, vehicle): the same vehicle is chosen on every rerun."""
    ins = sc.instrumented
    if ins.ids:
        return vid in ins.ids
    if ins.vtype:
        return vtype == ins.vtype
    h = hashlib.sha256(f"{sc.seed}|{run}|{vid}".encode()).digest()
    return int.from_bytes(h[:8], "little") / 2**64 < ins.penetration


# Peak memory of `simulate` per trajectory row on a section: 333 B measured on 268,000 rows
# (the per-step lists, the run's frame, their concatenation, macro statistics, CSV writing).
BYTES_PER_ROW = 384
MEMORY_CHECK_STEPS = 500


def check_run_memory(sc: SectionScenario, rows_per_run: float, run: int) -> None:
    """Refuse a ground truth whose trajectories will not fit in memory, projected from the
    rows of run ``run`` so far: how many vehicles drive on the section is known only then."""
    check_memory(
        rows_per_run * sc.simulation.n_runs * BYTES_PER_ROW,
        f"{sc.source}: about {rows_per_run:,.0f} trajectory rows per run (as run {run} goes) "
        f"x simulation.n_runs = {sc.simulation.n_runs}",
        "lower simulation.duration_s or n_runs, or choose a shorter section",
    )


def record_run(
    sim: Simulation, sc: SectionScenario, section: Section, run: int
) -> tuple[pd.DataFrame, dict[str, int]]:
    """Step one run; rows of every vehicle on the section after the warm-up."""
    dt = sc.simulation.step_length_s
    n_warm = int(round(sc.simulation.warmup_s / dt))
    n_rec = int(round(sc.simulation.duration_s / dt))
    types: dict[str, str] = {}
    classes: dict[str, str] = {}
    observed: dict[str, bool] = {}
    cols: dict[str, list] = {
        k: []
        for k in (
            "time_s",
            "vehicle_id",
            "lane_index",
            "edge_index",
            "arc_m",
            "speed_mps",
            "accel_mps2",
        )
    }
    lanes = section.lanes
    collisions = teleports = 0
    for step in range(n_warm + n_rec):
        sim.step()
        new = sim.departed()
        if new:
            sim.subscribe_lanes(new)
            for vid in new:
                types[vid] = sim.vehicle_type(vid)
                if types[vid] not in classes:
                    classes[types[vid]] = sim.vehicle_class(types[vid])
                observed[vid] = _is_instrumented(sc, vid, types[vid], run)
        collisions += sim.collisions()
        teleports += sim.teleports()
        if step < n_warm:
            continue
        if (step - n_warm + 1) % MEMORY_CHECK_STEPS == 0:
            check_run_memory(sc, len(cols["time_s"]) * n_rec / (step - n_warm + 1), run)
        t = round((step + 1) * dt, 6)
        for vid, (lane_id, pos, speed, accel) in sim.read_lane_states().items():
            hit = lanes.get(lane_id)
            if hit is None:
                continue
            e, idx, start, scale = hit
            cols["time_s"].append(t)
            cols["vehicle_id"].append(vid)
            cols["lane_index"].append(idx)
            cols["edge_index"].append(e)
            cols["arc_m"].append(start + pos * scale)
            cols["speed_mps"].append(speed)
            cols["accel_mps2"].append(accel)
    df = pd.DataFrame(cols)
    df.insert(0, "run", run)
    df.insert(3, "vtype", df["vehicle_id"].map(types))
    df.insert(4, "observed", df["vehicle_id"].map(observed).astype(bool))
    df = df.sort_values(["time_s", "lane_index", "arc_m"], kind="stable").reset_index(drop=True)
    stats = {
        "vehicles_seen": int(df["vehicle_id"].nunique()),
        "observed": int(df.loc[df["observed"], "vehicle_id"].nunique()),
        "collisions": collisions,
        "teleports": teleports,
        "vclass": classes,
    }
    return df, stats


def simulate_section(
    sc: SectionScenario, out: Path | str, command: str = "", progress: bool = True
) -> Path:
    """All ground-truth runs of a section scenario, written into ``out``."""
    inputs, section, vtypes = load_section(sc)
    placed = place_detectors(sc, inputs, section)
    out = prepare_out_dir(out)
    t_start = time.perf_counter()
    min_len = min(v.length_m for v in vtypes.values())
    with staging_dir(out) as stage:
        trajs, dets, passages, runs = [], [], [], []
        vclass: dict[str, str] = {}
        sim: Simulation | None = None
        try:
            for run in tqdm(
                range(sc.simulation.n_runs), desc="simulate", unit="run", disable=not progress
            ):
                run_dir = stage / "sumo" / f"run_{run:03d}"
                run_dir.mkdir(parents=True)
                (run_dir / "detectors.add.xml").write_text(
                    detectors_xml(placed, sc.detectors.interval_s)
                )
                adds = tuple(
                    _without_detectors(p, run_dir / f"user_{i}_{p.name}")
                    for i, p in enumerate(inputs.additional_files)
                )
                seed = sc.seed + run
                opts = SumoOptions(
                    inputs.net_file,
                    (*adds, run_dir / "detectors.add.xml"),
                    sc.simulation.step_length_s,
                    seed,
                    error_log=run_dir / "sumo.log",
                    route_files=inputs.route_files,
                    user_demand=True,
                )
                sim = Simulation(opts)
                df, stats = record_run(sim, sc, section, run)
                trajs.append(df)
                check_run_memory(sc, sum(len(d) for d in trajs) / (run + 1), run)
                vclass.update(stats.pop("vclass"))
                runs.append({"run": run, "sumo_seed": seed, **stats})
        finally:
            if sim is not None:
                sim.close()  # SUMO writes a run's detector files when the next load or close ends it
        for run in range(sc.simulation.n_runs):
            d, p = read_detectors(stage / "sumo" / f"run_{run:03d}", run, placed)
            dets.append(d)
            passages.append(p)
        traj = pd.concat(trajs, ignore_index=True)
        if traj.empty:
            raise UserError(
                f"{sc.source}: no vehicle drove on the section in {sc.simulation.duration_s:g} s "
                "after the warm-up; check section.edges against the demand's routes"
            )
        if not traj["observed"].any():
            raise UserError(
                f"{sc.source}: no instrumented vehicle drove on the section; raise "
                "instrumented.penetration or name other vtype/ids"
            )
        det = pd.concat(dets, ignore_index=True)
        if det.empty:
            raise UserError(f"{sc.source}: the section's detectors wrote no interval")
        pas = pd.concat(passages, ignore_index=True)
        end = sc.simulation.warmup_s + sc.simulation.duration_s
        min_spacing = min_len + sc.bounds.min_gap_m
        det_macro = detector_macro(det, pas, sc.simulation.warmup_s, min_spacing, section)
        tr_macro = trajectory_macro(
            traj, section, sc.detectors.interval_s, sc.simulation.warmup_s, end
        )
        k_df = k_estimates(
            traj, det_macro, section, sc.generator.snapshot_every_s, sc.detectors.k_window_s
        )
        vt = pd.DataFrame(
            [
                {
                    "vtype": v.id,
                    "car_follow_model": v.car_follow_model,
                    "vclass": vclass.get(v.id, "passenger"),
                    "length_m": v.length_m,
                    "min_gap_m": v.min_gap_m,
                    "vehicles": int(traj.loc[traj["vtype"] == v.id, "vehicle_id"].nunique()),
                }
                for v in vtypes.values()
            ]
        )
        section.write(stage / "section.json")
        write_csv(traj, stage / "trajectories.csv")
        write_csv(vt, stage / "vtypes.csv")
        write_csv(det, stage / "detectors.csv")
        write_csv(pas, stage / "detector_passages.csv")
        write_csv(pd.concat([det_macro, tr_macro], ignore_index=True), stage / "macro.csv")
        write_csv(k_df, stage / "k_estimate.csv")
        write_csv(pd.DataFrame(runs), stage / "runs.csv")
        manifest = build_manifest(sc, command, stage="simulate")
        manifest.update(
            section_length_m=section.length_m,
            section_lanes=section.n_lanes.tolist(),
            detectors={"source": placed[0].source, "count": len(placed)},
            car_following_models=sorted({v.car_follow_model for v in vtypes.values()}),
            collisions=int(sum(r["collisions"] for r in runs)),
            teleports=int(sum(r["teleports"] for r in runs)),
            k_estimate=k_summary(k_df, section),
            timings_s={"simulate": round(time.perf_counter() - t_start, 3)},
        )
        write_manifest(manifest, stage)
    return out


def k_summary(k_df: pd.DataFrame, section: Section) -> dict[str, float]:
    """The K estimate's error: mean, mean absolute, and mean absolute per lane."""
    if k_df.empty:
        return {"snapshots": 0}
    err = k_df["k_error"].to_numpy(dtype=float)
    lanes = float((section.n_lanes * section.lengths_m).sum() / section.lengths_m.sum())
    return {
        "snapshots": len(err),
        "mean_error_veh": float(err.mean()),
        "mean_abs_error_veh": float(np.abs(err).mean()),
        "mean_abs_error_per_lane_veh": float(np.abs(err).mean() / lanes),
        "mean_k_true": float(k_df["k_true"].mean()),
    }


# --------------------------------------------------------------------------- loading

TRAJ_COLUMNS = (
    "run",
    "time_s",
    "vehicle_id",
    "vtype",
    "observed",
    "lane_index",
    "edge_index",
    "arc_m",
    "speed_mps",
    "accel_mps2",
)
TRAJ_NUMBERS = tuple(c for c in TRAJ_COLUMNS if c not in ("vehicle_id", "vtype", "observed"))
MACRO_COLUMNS = (
    "run",
    "source",
    "begin_s",
    "end_s",
    "mean_speed_mps",
    "mean_spacing_m",
    "std_spacing_m",
    "speed_min_mps",
    "speed_max_mps",
)
K_COLUMNS = ("run", "time_s", "k_true", "k_est", "k_error")


def check_step_length(manifest: Path, sc: SectionScenario) -> None:
    """The ground truth of ``manifest`` was recorded every ``simulation.step_length_s`` of
    ``sc``: its recorded actions and replays are per step of that length."""
    try:
        have = json.loads(manifest.read_text())["scenario"]["simulation"]["step_length_s"]
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        raise UserError(
            f"{manifest}: unreadable ground-truth manifest, no simulation.step_length_s "
            "(run `macromicro simulate` on a section scenario)"
        ) from None
    want = sc.simulation.step_length_s
    if have != want:
        raise UserError(
            f"{manifest}: ground truth was simulated with simulation.step_length_s = {have}, "
            f"scenario {sc.source} has {want}"
        )


def load_section_truth(folder: Path | str, sc: SectionScenario | None = None) -> SectionTruth:
    """Read a section ground-truth folder; missing files are one-line errors, and so is a
    ground truth of another section or step length than ``sc``'s (every stage that reads one
    loads it here)."""
    folder = Path(folder)
    need = (
        "section.json",
        "trajectories.csv",
        "detectors.csv",
        "macro.csv",
        "vtypes.csv",
        "k_estimate.csv",
        "manifest.json",
    )
    for name in need:
        if not (folder / name).is_file():
            raise UserError(
                f"{folder / name}: missing (run `macromicro simulate` on a section scenario)"
            )
    manifest = read_manifest(folder / "manifest.json")
    check_outputs(folder, manifest, names=("section.json",))
    section = Section.read(folder / "section.json")
    if sc is not None and tuple(sc.section.edges) != section.edge_ids:
        raise UserError(
            f"{folder}: ground truth is for section {list(section.edge_ids)}, scenario {sc.source} "
            f"has {list(sc.section.edges)}"
        )
    if sc is not None:
        check_step_length(folder / "manifest.json", sc)
    # Each CSV is checked against the manifest's outputs map (rows and SHA-256).
    # Columns the later stages read must be there, states and counts finite numbers.
    traj = read_checked_csv(
        folder,
        "trajectories.csv",
        manifest,
        TRAJ_COLUMNS,
        TRAJ_NUMBERS,
        dtype={"vehicle_id": str, "vtype": str},
    )
    return SectionTruth(
        folder=folder,
        section=section,
        trajectories=traj,
        detectors=read_checked_csv(folder, "detectors.csv", manifest),
        macro=read_checked_csv(folder, "macro.csv", manifest, MACRO_COLUMNS, ("run",)),
        vtypes=read_checked_csv(
            folder,
            "vtypes.csv",
            manifest,
            ("vtype", "length_m", "vehicles"),
            ("length_m", "vehicles"),
            dtype={"vtype": str, "vclass": str},
        ),
        k_estimate=read_checked_csv(folder, "k_estimate.csv", manifest, K_COLUMNS, K_COLUMNS),
    )

"""Ground truth on a section of the user's network: their demand, their models, detectors.

SUMO runs the user's routes and flows with their vehicle types (whatever car-following
model they use: ``vtypes.csv`` records which). Every step, every vehicle on the section is
recorded in section coordinates (lane index, arc). Detectors are the user's own E1/E2 on
the section (re-created with our output files and interval, so nothing is written next to
the user's files) or, where there are none, E1 loops placed every ``auto_spacing_m`` on
every lane (``truth/section_detectors.py``). An instantaneous loop sits beside every E1
loop: its per-vehicle passages give the spread of the spacings, as on the ring. The macro
statistics are ``truth/section_macro.py``'s, the K estimates ``truth/hidden_count.py``'s.
Instrumented vehicles are chosen by a penetration rate, a vType or explicit IDs.

This module: the runs, ``simulate_section`` (writes) and ``load_section_truth`` (reads).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd

from macromicro_sumo.data.section import SIGNAL_COLUMNS, SectionTruth, vehicle_level
from macromicro_sumo.errors import UserError
from macromicro_sumo.fielddata.schema import TRAJ_COLUMNS
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
from macromicro_sumo.road.section import Section, read_section
from macromicro_sumo.scenario.fleet import fleet_demand
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.demand import VType, check_demand, check_vehicle_ids
from macromicro_sumo.sumo.fleet import FLEET_ROUTE_PREFIX
from macromicro_sumo.sumo.inputs import SumoInputs, read_net, scenario_inputs
from macromicro_sumo.sumo.simulation import Driver, Simulation, SumoOptions
from macromicro_sumo.truth import fleet
from macromicro_sumo.truth.files import truth_from_files
from macromicro_sumo.truth.hidden_count import k_estimates
from macromicro_sumo.truth.section_detectors import (
    detectors_xml,
    place_detectors,
    read_detectors,
    without_detectors,
)
from macromicro_sumo.truth.section_macro import detector_macro, k_summary, trajectory_macro
from macromicro_sumo.truth.section_rows import SectionRows
from macromicro_sumo.truth.section_speed import edie_speeds, stop_line_edges
from macromicro_sumo.truth.signals import SignalRecorder
from macromicro_sumo.truth.stations import PASSAGE_LAG_STEPS, StationRecord, side_junction_arcs
from macromicro_sumo.truth.vtypes import vtype_frame


def load_section(sc: SectionScenario) -> tuple[SumoInputs, Section, dict[str, VType]]:
    """Inputs, the section and the vehicle types, every check done before SUMO starts."""
    inputs = scenario_inputs(sc)
    section = read_section(inputs.net_file, list(sc.section.edges), sc.section.closed, sc.source)
    demand = fleet_demand(sc)
    if demand is None:
        vtypes = check_demand(inputs, read_net(inputs.net_file))
    else:  # the fleet's vehicles, each its own vType named as it
        vtypes = fleet.fleet_vtypes(demand, fleet.section_ring(section, sc.source), sc.source)
    if sc.instrumented.vtype and sc.instrumented.vtype not in vtypes:
        raise UserError(
            f"{sc.source}: instrumented.vtype = {sc.instrumented.vtype!r} is not a vType of the "
            f"demand; accepted: one of {', '.join(sorted(vtypes))}"
        )
    if demand is None:
        check_vehicle_ids(inputs, sc.instrumented.ids, f"{sc.source}: instrumented.ids")
    elif set(sc.instrumented.ids) - set(vtypes):
        raise UserError(
            f"{sc.source}: instrumented.ids names {sorted(set(sc.instrumented.ids) - set(vtypes))}"
            f"; the fleet's vehicles are v0 .. v{len(vtypes) - 1}"
        )
    return inputs, section, vtypes


def fleet_specs(sc: SectionScenario, section: Section) -> tuple[Section, list[fleet.RunSpec]]:
    """A fleet scenario's ring and every run's draws from ``sc.seed`` (the ring truth's)."""
    demand = fleet_demand(sc)
    if demand is None:
        raise UserError(f"{sc.source}: no [fleet] table: the demand is the route files")
    geo = fleet.section_ring(section, sc.source)
    return geo, fleet.run_specs(demand, geo, sc.simulation.n_runs, sc.seed)


# --------------------------------------------------------------------------- runs


def is_instrumented(sc: SectionScenario, vid: str, vtype: str, run: int) -> bool:
    """Deterministic per (seed, run, vehicle): the same vehicle is chosen on every rerun."""
    ins = sc.instrumented
    if ins.ids:
        return vid in ins.ids
    if ins.vtype:
        return vtype == ins.vtype
    return vehicle_level(sc.seed, run, vid) < ins.penetration


# Peak memory of `simulate` per trajectory row on a section: 333 B measured on 268,000 rows
# (the per-step lists, the run's frame, their concatenation, macro statistics, CSV writing).
BYTES_PER_ROW = 384
MEMORY_CHECK_STEPS = 500


def check_run_memory(sc: SectionScenario, rows_per_run: float, run: int | None) -> None:
    """Refuse trajectories too large for memory, from run ``run``'s rows (None: a fleet's)."""
    how = "a fleet's" if run is None else f"as run {run} goes"
    check_memory(
        rows_per_run * sc.simulation.n_runs * BYTES_PER_ROW,
        f"{sc.source}: about {rows_per_run:,.0f} trajectory rows per run ({how}) "
        f"x simulation.n_runs = {sc.simulation.n_runs}",
        "lower simulation.duration_s or n_runs, or choose a shorter section",
    )


def record_run(
    sim: Simulation,
    sc: SectionScenario,
    section: Section,
    run: int,
    driver: Driver | None = None,
    fleet_run: tuple[fleet.RunSpec, Section] | None = None,
) -> tuple[pd.DataFrame, dict[str, int]]:
    """Step one run; rows of every vehicle on the section after the warm-up. ``driver``
    (a deployment) acts before every step; None: SUMO drives every vehicle. ``fleet_run``:
    the run's fleet draws, inserted before the first step and checked after it."""
    if fleet_run is not None:
        fleet.insert_fleet(sim, *fleet_run, FLEET_ROUTE_PREFIX)
    dt = sc.simulation.step_length_s
    n_warm = int(round(sc.simulation.warmup_s / dt))
    n_rec = int(round(sc.simulation.duration_s / dt))
    types: dict[str, str] = {}
    classes: dict[str, tuple[str, float]] = {}  # vType -> SUMO's (vClass, decel [m/s^2])
    # The rows: each step's read kept, filtered to the section every memory check and at
    # the end (a row per vehicle in Python cost the recording more than SUMO's own step).
    rows = SectionRows(section)
    collisions = teleports = 0
    signals = SignalRecorder(sim, section)
    record_signals = signals.record if signals.links else None  # none: nothing to call
    for step in range(n_warm + n_rec):
        if driver is not None:
            driver.before_step(sim)
        sim.step()
        new = sim.departed()
        for vid in new:
            vt = types[vid] = sim.vehicle_type(vid)
            if vt not in classes:
                classes[vt] = (sim.vehicle_class(vt), sim.vtype_shape(vt)[2])
        collisions += sim.collisions()
        teleports += sim.teleports()
        if step == 0 and fleet_run is not None:
            fleet.check_fleet_inserted(sim, *fleet_run)
        if step < n_warm:
            continue
        if (step - n_warm + 1) % MEMORY_CHECK_STEPS == 0:
            check_run_memory(sc, rows.flush() * n_rec / (step - n_warm + 1), run)
        if record_signals is not None:
            record_signals(sim, round((step + 1) * dt, 6))
        rows.add(round((step + 1) * dt, 6), sim.vehicle_states())
    # Each vehicle's draw from its departure's vType, after the run: the same dict; its hash
    # between SUMO's steps cost 10-21 us a vehicle, here 2 (thread CPU, Bremen, load 2-8).
    observed = {vid: is_instrumented(sc, vid, vt, run) for vid, vt in types.items()}
    df, seen, seen_observed = rows.frame(run, types, observed)
    if fleet_run is not None and len(df) != n_rec * len(fleet_run[0].params):
        # A closed road keeps its fleet: a vehicle missing from a step left the road.
        raise UserError(
            f"run {run}: {len(df)} recorded rows, expected {n_rec} steps x "
            f"{len(fleet_run[0].params)} vehicles (a fleet vehicle left the section)"
        )
    stats = {
        "vehicles_seen": seen,
        "observed": seen_observed,
        "collisions": collisions,
        "teleports": teleports,
        "vclass": classes,
        "signals": signals.frame(run),
    }
    return df, stats


def run_section(
    sc: SectionScenario,
    inputs: SumoInputs,
    section: Section,
    placed: list,
    stage: Path,
    runs: Sequence[int],
    progress: bool = True,
    driver_for: Callable[[int], Driver | None] | None = None,
    desc: str = "simulate",
    rng_streams: int | None = None,
) -> tuple[list[pd.DataFrame], list[dict], dict[str, tuple[str, float]]]:
    """Step ``runs`` (SUMO seed ``sc.seed + run``, random streams ``rng_streams``), SUMO's
    files under ``stage/sumo``; returns (trajectory frames, runs.csv rows, vType -> (vClass,
    decel)). ``driver_for(run)``: who drives in that run besides SUMO (a deployment)."""
    trajs, rows = [], []
    vclass: dict[str, tuple[str, float]] = {}
    demand = fleet_demand(sc)
    if demand is not None:
        steps = sc.simulation.duration_s / sc.simulation.step_length_s  # refuse before draws
        check_run_memory(sc, demand.fleet.n_vehicles * steps, None)
        geo, specs = fleet_specs(sc, section)
    sim: Simulation | None = None
    try:
        for run in tqdm(runs, desc=desc, unit="run", disable=not progress):
            run_dir = stage / "sumo" / f"run_{run:03d}"
            run_dir.mkdir(parents=True)
            (run_dir / "detectors.add.xml").write_text(
                detectors_xml(placed, sc.detectors.interval_s)
            )
            adds = tuple(
                without_detectors(p, run_dir / f"user_{i}_{p.name}")
                for i, p in enumerate(inputs.additional_files)
            )
            seed = sc.seed + run
            fleet_run = None
            if demand is not None:  # the fleet's own seed and files; placed exactly
                fleet_run = (specs[run], geo)
                seed = specs[run].sumo_seed
                span_s = sc.simulation.warmup_s + sc.simulation.duration_s
                dt = sc.simulation.step_length_s
                adds += fleet.write_fleet_inputs(run_dir, specs[run], geo, demand, dt, span_s)
            opts = SumoOptions(
                inputs.net_file,
                (*adds, run_dir / "detectors.add.xml"),
                sc.simulation.step_length_s,
                seed,
                error_log=run_dir / "sumo.log",
                route_files=inputs.route_files,
                user_demand=demand is None,
                rng_streams=rng_streams,
            )
            sim = Simulation(opts)
            driver = driver_for(run) if driver_for is not None else None
            df, stats = record_run(sim, sc, section, run, driver, fleet_run)
            trajs.append(df)
            check_run_memory(sc, sum(len(d) for d in trajs) / len(trajs), run)
            vclass.update(stats.pop("vclass"))
            if not (signals := stats.pop("signals")).empty:  # signals.csv's rows of the run
                signals.to_csv(run_dir / "signals.csv", index=False)
            rows.append({"run": run, "sumo_seed": seed, **stats})
    finally:
        if sim is not None:
            sim.close()  # SUMO writes a run's detector files when the next load or close ends it
    return trajs, rows, vclass


def read_run_detectors(
    stage: Path, runs: Sequence[int], placed: list
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """detectors.csv and detector_passages.csv of ``runs`` from SUMO's files in ``stage``."""
    dets, passages = [], []
    for run in runs:
        d, p = read_detectors(stage / "sumo" / f"run_{run:03d}", run, placed)
        dets.append(d)
        passages.append(p)
    return pd.concat(dets, ignore_index=True), pd.concat(passages, ignore_index=True)


def section_macro(
    sc: SectionScenario,
    section: Section,
    traj: pd.DataFrame,
    det: pd.DataFrame,
    pas: pd.DataFrame,
    vtypes: dict[str, VType],
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """macro.csv's two parts: the detectors' statistics and the trajectories', per interval."""
    end = sc.simulation.warmup_s + sc.simulation.duration_s
    min_spacing = min(v.length_m for v in vtypes.values()) + sc.bounds.min_gap_m
    det_macro = detector_macro(det, pas, sc.simulation.warmup_s, min_spacing, section)
    tr_macro = trajectory_macro(traj, section, sc.detectors.interval_s, sc.simulation.warmup_s, end)
    return det_macro, tr_macro


def simulate_section(
    sc: SectionScenario, out: Path | str, command: str = "", progress: bool = True
) -> Path:
    """All ground-truth runs of a section scenario, written into ``out``."""
    if sc.data.source == "files":  # field data instead of SUMO runs (truth/files.py)
        return truth_from_files(sc, out, command, progress)
    inputs, section, vtypes = load_section(sc)
    placed = place_detectors(sc, inputs, section)
    out = prepare_out_dir(out)
    t_start = time.perf_counter()
    all_runs = range(sc.simulation.n_runs)
    with staging_dir(out) as stage:
        trajs, runs, vclass = run_section(sc, inputs, section, placed, stage, all_runs, progress)
        det, pas = read_run_detectors(stage, all_runs, placed)
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
        if det.empty:
            raise UserError(f"{sc.source}: the section's detectors wrote no interval")
        det_macro, tr_macro = section_macro(sc, section, traj, det, pas, vtypes)
        # Input-output counts between full stations and the end pieces from the passages in
        # every regime: anchored together, weighted to free-flowing intervals, once for the
        # record where no ramp lies between stations, they beat the density estimate in
        # free flow too (docs/sections.md, "Hidden count"; scripts/bench_hidden_count.py).
        net = read_net(inputs.net_file)
        record = StationRecord(
            det,
            pas,
            side_junction_arcs(net, section),
            PASSAGE_LAG_STEPS * sc.simulation.step_length_s,
            from_empty=fleet_demand(sc) is None,  # SUMO starts empty; a fleet on the section
        )
        k_df = k_estimates(
            traj, det_macro, section, sc.generator.snapshot_every_s, sc.detectors.k_window_s, record
        )
        if stop_line_edges(section, net):  # queues stand between the loops: Edie's speed
            det_macro = edie_speeds(det_macro, record, section, sc.simulation.step_length_s)
        vt = vtype_frame(vtypes, vclass, traj)
        section.write(stage / "section.json")
        write_csv(traj, stage / "trajectories.csv")
        write_csv(vt, stage / "vtypes.csv")
        write_csv(det, stage / "detectors.csv")
        write_csv(pas, stage / "detector_passages.csv")
        write_csv(pd.concat([det_macro, tr_macro], ignore_index=True), stage / "macro.csv")
        write_csv(k_df, stage / "k_estimate.csv")
        write_csv(pd.DataFrame(runs), stage / "runs.csv")
        if sig := sorted((stage / "sumo").glob("run_*/signals.csv")):
            write_csv(pd.concat(map(pd.read_csv, sig), ignore_index=True), stage / "signals.csv")
        if fleet_demand(sc) is not None:  # the draws, as the ring truth writes them
            geo, specs = fleet_specs(sc, section)
            write_csv(
                pd.concat([s.params for s in specs], ignore_index=True), stage / "vehicles.csv"
            )
            write_csv(fleet.limits_frame(specs, geo), stage / "speed_limits.csv")
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


# --------------------------------------------------------------------------- loading

# The columns are the ground truth's schema, one definition with the field-data readers'.
TRAJ_NUMBERS = tuple(c for c in TRAJ_COLUMNS if c not in ("vehicle_id", "vtype", "observed"))
MACRO_COLUMNS = ("run", "source", "begin_s", "end_s", "mean_speed_mps", "mean_spacing_m")
MACRO_COLUMNS += ("std_spacing_m", "speed_min_mps", "speed_max_mps")
K_COLUMNS = ("run", "time_s", "k_true", "k_est", "k_error")
SIGNAL_TEXT = {"signal_id": str, "program": str, "state": str}


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
    need = ("section.json", "trajectories.csv", "detectors.csv", "macro.csv", "vtypes.csv")
    for name in (*need, "k_estimate.csv", "manifest.json"):
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
        signals=(  # optional: a truth without signals on its section has none
            read_checked_csv(folder, "signals.csv", manifest, SIGNAL_COLUMNS, dtype=SIGNAL_TEXT)
            if (folder / "signals.csv").is_file()
            else None
        ),
    )

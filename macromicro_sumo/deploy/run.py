"""One method deployed over whole runs: the ground truth's run loops with a driver.

``load_context`` reads what every deployment of a scenario shares: the held-out runs of
its ground truth and how to re-run them with the same seeds (SUMO seed ``sc.seed + run``;
a fleet's draws per run from ``sc.seed``), so that the only difference from the ground truth is who drives. ``run_method`` steps some of
those runs with a method's driver and returns the outputs in the ground truth's schemas
(``DeployResult``); ``write_method`` writes them into one method's folder.

A method that switches the driven vehicles to an IDM vType takes its parameters ``theta``
(SUMO's attribute names: accel, decel, tau, minGap, speedFactor and optionally delta), so a
calibration (``deploy.calibrate``) can deploy any candidate through ``run_method``.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import run_limits_mps, split_runs
from macromicro_sumo.deploy.drivers import ActionBatch, SectionDriver, SectionSpeedDriver
from macromicro_sumo.deploy.field import (
    check_station_grid,
    demand_files,
    sampled_demand,
    station_loops,
)
from macromicro_sumo.deploy.intervals import interval_length_s
from macromicro_sumo.deploy.population import SAFETY_COLUMNS, SwitchedType
from macromicro_sumo.deploy.redraw_driver import SectionRedrawDriver
from macromicro_sumo.deploy.type_driver import SectionTypeDriver
from macromicro_sumo.env.driver_speed import resolved_entry
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import write_csv, write_manifest
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.demand import VType, check_demand
from macromicro_sumo.sumo.inputs import SumoInputs, read_net, scenario_inputs
from macromicro_sumo.truth.section import (
    load_section,
    load_section_truth,
    read_run_detectors,
    run_section,
    section_macro,
)
from macromicro_sumo.truth.section_detectors import place_detectors

# A run's random streams, numpy seeds [seed, run, stream]: its sampled actions (``sampled``)
# and oracle_population's redrawn drivers, apart from the vType switch's speed factors (17).
ACTION_STREAM = 30
REDRAW_STREAM = 31


@dataclass(frozen=True)
class Drive:
    """How a method drives: ``act`` (speed commands, through the safety layer ``safety``;
    None: the scenario's ``deploy.safety``; drawn around it with ``sample_std_mps2``),
    ``theta`` (an IDM vType with these parameters), ``defaults`` (SUMO's default model and
    parameters of each vClass), or nothing of these (the oracle: SUMO drives every vehicle with its true model);
    ``rng_streams``: SUMO's driving random streams re-mapped (``SumoOptions.rng_streams``;
    None: as the ground truth's runs); ``redraw``: nobody driven, each population vehicle's
    own draws redrawn (``SectionRedrawDriver``)."""

    act: ActionBatch | None = None
    theta: dict[str, float] | None = None
    defaults: bool = False
    safety: str | None = None
    # ``deploy.action = "sample"``: each step's action drawn from N(act, sample_std^2)
    # [m/s^2] per driven vehicle (``sampled``); 0: ``act`` itself, the policy's mean.
    sample_std_mps2: float = 0.0
    rng_streams: int | None = None
    redraw: bool = False
    # ``deploy.safety_floor_on`` for ``act``'s commands: "all" or "standing" (None: the
    # scenario's; "auto" is chosen before, ``deploy.floor_choice``).
    floor_on: str | None = None


@dataclass
class DeployContext:
    """What every deployment of one scenario shares (``load_context``)."""

    sc: Any
    truth_dir: Path
    held_out: list[int]
    section: Section | None = None
    inputs: SumoInputs | None = None
    placed: list | None = None
    vtypes: dict[str, VType] | None = None
    vclass: dict[str, str] | None = None  # demand vType -> vClass (from vtypes.csv)
    run_sections: dict[int, Section] | None = None  # each run's limits (a fleet's drawn ones)
    # Field data: each run's own inputs (a demand sampled from its stations), how the
    # demand was made (every manifest records it), and the folder that holds it.
    run_inputs: dict[int, SumoInputs] | None = None
    demand: dict[str, Any] | None = None
    scratch: tempfile.TemporaryDirectory | None = None


@dataclass
class DeployResult:
    """A deployment's outputs over its runs, in the ground truth's schemas."""

    trajectories: pd.DataFrame
    detectors: pd.DataFrame
    passages: pd.DataFrame
    macro: pd.DataFrame
    runs: pd.DataFrame


def load_context(sc: SectionScenario, truth_dir: Path | str) -> DeployContext:
    """The held-out runs of the ground truth in ``truth_dir`` and how to re-run them."""
    truth_dir = Path(truth_dir)
    if sc.data.source == "files":
        return files_context(sc, truth_dir)
    truth = load_section_truth(truth_dir, sc)
    check_truth_seed(sc, truth_dir)
    # policy.driver_entry "auto": the drivers read the rule Stage II's banks read (the train
    # + val runs' observed drivers); the stage's manifest keeps the scenario's "auto"
    sc = resolved_entry(sc, truth)[0]
    held = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["held_out"]
    inputs, section, vtypes = load_section(sc)
    if sc.deploy.vtype and sc.deploy.vtype not in vtypes:
        raise UserError(
            f"{sc.source}: deploy.vtype = {sc.deploy.vtype!r} is not a vType of the demand; "
            f"accepted: one of {', '.join(sorted(vtypes))}"
        )
    vt = truth.vtypes
    vclass = dict(zip(vt["vtype"], vt["vclass"].astype(str), strict=True))
    return DeployContext(
        sc,
        truth_dir,
        [int(r) for r in held],
        section=section,
        inputs=inputs,
        placed=place_detectors(sc, inputs, section),
        vtypes=vtypes,
        vclass=vclass,
        # Every run's, not the held-out runs' only: a run deployed without its own drawn
        # limits would fall back to the network's (a script deploying every run did).
        run_sections={
            int(r): dataclasses.replace(section, limits_mps=lim)
            for r, lim in zip(truth.runs, run_limits_mps(truth, truth.runs), strict=True)
        },
    )


def check_truth_seed(sc: SectionScenario, truth_dir: Path) -> None:
    """A section's runs are re-run with SUMO seed ``sc.seed + run`` (a fleet's from
    ``sc.seed``) and their instrumented vehicles drawn from ``sc.seed``: another seed than the
    ground truth's re-runs other runs and compares them with the recorded ones."""
    manifest = truth_dir / "manifest.json"
    recorded = json.loads(manifest.read_text()).get("seed") if manifest.is_file() else None
    if recorded is not None and int(recorded) != sc.seed:
        raise UserError(
            f"{sc.source}: seed = {sc.seed}, but the ground truth {truth_dir} was simulated "
            f"with seed {recorded}: the deployment would re-run other runs; accepted: seed = "
            f"{recorded} (or re-run `macromicro simulate`)"
        )


def files_context(sc: SectionScenario, truth_dir: Path) -> DeployContext:
    """A deployment on field data (``deploy.field``): loops at the stations, SUMO from t = 0
    to the stations' last interval, and the scenario's route files as the demand, or where
    it has none a demand per held-out recording sampled from its station counts."""
    truth = load_section_truth(truth_dir, sc)
    sc = resolved_entry(sc, truth)[0]  # policy.driver_entry "auto", as load_context
    runs = [int(r) for r in truth.runs]
    held = [
        int(r) for r in split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["held_out"]
    ]
    inputs, section = scenario_inputs(sc), truth.section
    det = truth.detectors
    interval = interval_length_s(det)
    check_station_grid(det, interval, str(truth_dir / "detectors.csv"))
    end = float(det["end_s"].max())
    warmup = sc.simulation.warmup_s
    if end <= warmup:
        raise UserError(
            f"{sc.source}: simulation.warmup_s = {warmup:g} s leaves no station interval to "
            f"compare (the last ends at {end:g} s); accepted: warmup_s < {end:g}"
        )
    # The run covers the stations (the warm-up fills the empty road; deploy.compare leaves
    # its intervals out); the loops aggregate as the stations do.
    run_sc = dataclasses.replace(
        sc,
        simulation=dataclasses.replace(sc.simulation, duration_s=end - warmup),
        detectors=dataclasses.replace(sc.detectors, interval_s=interval),
    )
    scratch, run_inputs = None, None
    if inputs.route_files:
        demand = {"source": "route files", "files": [str(p) for p in inputs.route_files]}
    else:
        scratch = tempfile.TemporaryDirectory(prefix="macromicro_demand_")
        types, routes = sampled_demand(
            inputs.net_file,
            section,
            det,
            truth.vtypes,
            runs,  # every recording: the detector calibration deploys the training ones
            Path(scratch.name),
            sc.seed,
            (warmup, end),
        )
        run_inputs = {r: dataclasses.replace(inputs, route_files=(types, routes[r])) for r in runs}
        demand = {
            "source": "routeSampler.py on the station counts",
            "window_s": [warmup, end],
            "files": {str(r): routes[r].name for r in runs},
        }
    net = read_net(inputs.net_file)
    vtypes: dict[str, VType] = {}
    for i in run_inputs.values() if run_inputs else [inputs]:
        vtypes |= check_demand(i, net)
    if sc.deploy.vtype and sc.deploy.vtype not in vtypes:
        raise UserError(
            f"{sc.source}: deploy.vtype = {sc.deploy.vtype!r} is not a vType of the demand; "
            f"accepted: one of {', '.join(sorted(vtypes))}"
        )
    vt = truth.vtypes
    return DeployContext(
        run_sc,
        truth_dir,
        held,
        section=section,
        inputs=inputs,
        placed=station_loops(det, section, interval),
        vtypes=vtypes,
        vclass=dict(zip(vt["vtype"].astype(str), vt["vclass"].astype(str), strict=True)),
        run_inputs=run_inputs,
        demand=demand,
        scratch=scratch,
    )


# --------------------------------------------------------------------------- vTypes


def vtype_xml(rows: dict[str, tuple[str, float]], drive: Drive) -> tuple[str, dict]:
    """(additional-file XML, demand vType -> switched vType) for a vType-switching method.

    ``rows``: demand vType -> (vClass, length). Defaults: only vClass and length are given,
    SUMO fills in its model and parameters for that vClass. IDM: ``theta``'s parameters with
    SUMO's own IDM integration (its default ``stepping``), no speed deviation (the vehicles
    get ``theta``'s speedFactor).
    """
    lines, type_of = [], {}
    for i, (vt, (vclass, length)) in enumerate(sorted(rows.items())):
        tid = f"deploy_{i}"
        type_of[vt] = tid
        attrs = f'id="{tid}" vClass="{vclass}" length="{length:g}"'
        if drive.theta is not None:
            th = drive.theta
            attrs += (
                f' carFollowModel="IDM" accel="{th["accel"]:.4f}" decel="{th["decel"]:.4f}"'
                f' tau="{th["tau"]:.4f}" minGap="{th["minGap"]:.4f}"'
                f' delta="{th.get("delta", 4.0):g}" speedFactor="{th["speedFactor"]:.4f}"'
                f' speedDev="0"'
            )
        lines.append(f"    <vType {attrs}/>")
    return "<additional>\n" + "\n".join(lines) + "\n</additional>\n", type_of


def _switch_file(ctx: DeployContext, drive: Drive, stage: Path) -> tuple[tuple[Path, ...], dict]:
    """The additional file with the vTypes a method switches to (none for the others)."""
    if drive.theta is None and not drive.defaults:
        return (), {}
    rows = {v: (ctx.vclass.get(v, "passenger"), t.length_m) for v, t in ctx.vtypes.items()}
    text, type_of = vtype_xml(rows, drive)
    path = stage / "sumo" / "deploy_vtypes.add.xml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return (path,), type_of


# --------------------------------------------------------------------------- runs


def run_method(
    ctx: DeployContext,
    drive: Drive,
    stage: Path,
    runs: list[int] | None = None,
    progress: bool = False,
    desc: str = "deploy",
) -> DeployResult:
    """Step ``runs`` (default: the held-out ones) with ``drive``; SUMO's files under
    ``stage/sumo``."""
    runs = ctx.held_out if runs is None else runs
    extra, type_of = _switch_file(ctx, drive, stage)
    drivers: dict[int, Any] = {}
    speed = drive.theta["speedFactor"] if drive.theta is not None else None
    sc = ctx.sc

    def switch(run: int) -> SwitchedType:
        return SwitchedType(type_of, speed, np.random.default_rng([sc.seed, run, 17]))

    result = _section_runs(ctx, drive, stage, runs, extra, switch, drivers, progress, desc)
    counts = pd.DataFrame([{"run": r, **drivers[r].stats.as_dict()} for r in runs])
    result.runs = result.runs.merge(counts, on="run", how="left")
    return result


def sampled(act: ActionBatch, std_mps2: float, rng: np.random.Generator) -> ActionBatch:
    """``act`` as a Gaussian policy acts (``deploy.action = "sample"``): each call's mean
    actions plus ``std_mps2`` times standard normal draws from ``rng``, one per vehicle in
    the order given (the driver's, sorted by ID), still one batched call per step. The
    bounds, the maxSpeed cap and the safety layer apply to the draw
    (``deploy.safety.speed_commands``), as the env clips its sample to the bounds."""

    def draw(obs: np.ndarray) -> np.ndarray:
        mean = act(obs)
        return mean + std_mps2 * rng.standard_normal(len(mean))

    # policy.driver_speed: each driver's factor, as the mean action's (``deploy.drivers``)
    draw.driver_speeds = getattr(act, "driver_speeds", None)
    draw.driver_taus = getattr(act, "driver_taus", None)  # policy.driver_follow's, too
    draw.stop_gap_m = getattr(act, "stop_gap_m", None)  # the mean's prior (observe_rows)
    draw.prior_accel_mps2 = getattr(act, "prior_accel_mps2", None)  # command_dawdle "auto"
    return draw


def _section_runs(ctx, drive, stage, runs, extra, switch, drivers, progress, desc):
    sc = ctx.sc

    def driver_for(run: int) -> SectionDriver:
        # The run's own speed limits where the truth drew them (a fleet), as Stage II observed.
        args = (sc, (ctx.run_sections or {}).get(run, ctx.section), run)
        if drive.act is not None:
            act = drive.act
            if drive.sample_std_mps2 > 0.0:  # a generator per run: the same whatever ran before
                rng = np.random.default_rng([sc.seed, run, ACTION_STREAM])
                act = sampled(act, drive.sample_std_mps2, rng)
            if drive.floor_on is not None:  # the scenario's copy the driver reads it from
                dep = dataclasses.replace(sc.deploy, safety_floor_on=drive.floor_on)
                args = (dataclasses.replace(sc, deploy=dep), *args[1:])
            d = SectionSpeedDriver(*args, act, drive.safety or sc.deploy.safety)
        elif drive.theta is not None or drive.defaults:
            d = SectionTypeDriver(*args, switch(run))
        elif drive.redraw:
            d = SectionRedrawDriver(*args, np.random.default_rng([sc.seed, run, REDRAW_STREAM]))
        else:
            d = SectionDriver(*args)
        drivers[run] = d
        return d

    def with_extra(inputs: SumoInputs) -> SumoInputs:
        adds = (*inputs.additional_files, *extra)
        return dataclasses.replace(inputs, additional_files=adds) if extra else inputs

    if ctx.run_inputs is None:
        trajs, rows, _ = run_section(
            sc,
            with_extra(ctx.inputs),
            ctx.section,
            ctx.placed,
            stage,
            runs,
            progress,
            driver_for,
            desc,
            drive.rng_streams,
        )
    else:  # field data without route files: each recording has its own sampled demand
        trajs, rows = [], []
        for run in runs:
            t, r, _ = run_section(
                sc,
                with_extra(ctx.run_inputs[run]),
                ctx.section,
                ctx.placed,
                stage,
                [run],
                progress,
                driver_for,
                desc,
                drive.rng_streams,
            )
            trajs += t
            rows += r
    det, pas = read_run_detectors(stage, runs, ctx.placed)
    traj = pd.concat(trajs, ignore_index=True)
    det_macro, tr_macro = section_macro(sc, ctx.section, traj, det, pas, ctx.vtypes)
    macro = pd.concat([det_macro, tr_macro], ignore_index=True)
    return DeployResult(traj, det, pas, macro, pd.DataFrame(rows))


# --------------------------------------------------------------------------- writing


def first_seconds(traj: pd.DataFrame, seconds: float) -> pd.DataFrame:
    """The rows of each run's first ``seconds`` recorded seconds (FCD kept small)."""
    t0 = traj.groupby("run")["time_s"].transform("min")
    return traj[traj["time_s"] < t0 + seconds - 1e-9].reset_index(drop=True)


def write_method(
    ctx: DeployContext, res: DeployResult, folder: Path, manifest: dict[str, Any]
) -> dict[str, int]:
    """One method's folder (SUMO's files already in ``folder/sumo``) and its manifest;
    returns the runs' totals of ``SAFETY_COLUMNS`` (written into the manifest too)."""
    sc = ctx.sc
    write_csv(first_seconds(res.trajectories, sc.deploy.fcd_s), folder / "trajectories.csv")
    write_csv(res.detectors, folder / "detectors.csv")
    write_csv(res.passages, folder / "detector_passages.csv")
    write_csv(res.macro, folder / "macro.csv")
    write_csv(res.runs, folder / "runs.csv")
    ctx.section.write(folder / "section.json")
    totals = {c: int(res.runs[c].sum()) for c in SAFETY_COLUMNS}
    if ctx.demand is not None:  # field data: which demand was deployed, kept beside SUMO's files
        manifest = {**manifest, "demand": ctx.demand}
        if ctx.scratch is not None:
            for run in sorted(res.runs["run"]):
                for path in demand_files(Path(ctx.scratch.name), int(run)):
                    shutil.copy2(path, folder / "sumo" / path.name)
    write_manifest({**manifest, **totals}, folder)
    return totals

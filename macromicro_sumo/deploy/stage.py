"""Stage III: every method deployed population-wide on the held-out runs (``deploy``).

The methods (``DEPLOY_METHODS``; names as the evaluation's where they are the same method):

* ``policy``, ``micro_only``, ``macro_only``: the learned checkpoints, speed commands from
  the policy's deterministic mean action (``deploy.action = "sample"``: a draw from its
  Gaussian, ``deploy.run.sampled``), one batched call per step for every driven vehicle
  (``deploy.drivers``), through the safety layer ``deploy.safety`` (with
  ``deploy.safety_floor_on = "auto"`` its floor chosen first on training runs,
  ``deploy.floor_choice``);
* ``policy_no_safety``: the learned ``policy`` with its commands applied exactly
  (``safety = "none"``), beside it: what the safety layer changes, and why it is on (a
  collision here is a figure of the summary, not an error);
* ``idm_calibrated``: the IDM least-squares-fitted to the observed vehicles' (observation,
  action) pairs of the training runs, as the evaluation fits it (``evaluation.idm_fit``),
  applied by switching the driven vehicles to an IDM vType with those parameters: SUMO's
  own IDM drives them (with its own leaders, red lights and right of way);
* ``idm_detectors``: an IDM vType whose parameters are fitted to the TRAINING runs'
  detectors by a black-box search over whole SUMO runs (``deploy.calibrate``; budget
  ``deploy.calibration_budget_s`` and ``deploy.calibration_evals``), then deployed on the
  held-out runs like the others; its folder holds calibration_history.csv;
* ``sumo_default``: the driven vehicles switched to a vType with SUMO's default model and
  parameters of their vClass, only length and vClass kept: what a user gets without
  calibration;
* ``oracle``: nobody is switched; SUMO drives every vehicle with its true model and
  parameters, so its detector outputs are the ground truth's;
* ``oracle_redrawn``: the oracle with SUMO's driving random streams re-mapped
  (``REDRAWN_RNG_STREAMS``): the same demand, departures, drivers and speed factors, other
  random draws (Krauss' dawdling, lane-change randomness). What no model can know: its
  figures are the floor of the station-interval targets on this truth (docs/deploy-log.md,
  "What a near-exact model reaches");
* ``oracle_population``: ``oracle_redrawn`` with each driven vehicle's own draws redrawn
  from its population (``deploy.redraw_driver``): a perfect model of the population that
  knows nothing of each driver.

A method that is "an IDM vType with parameters theta" is ``Drive(theta=...)``
(``deploy.run``).

Who is driven (``deploy.population``): on a section every vehicle that is not instrumented,
or, with ``instrumented.hidden = "snapshot"``, every vehicle (nobody is instrumented for
good: the paper's ring, its whole fleet); ``deploy.share`` and ``deploy.vtype``
narrow it. The calibration of ``idm_detectors`` drives the same population.

Outputs: ``out/<method>/`` per method (``deploy.run.write_method``: the ground truth's
files for the held-out runs, runs.csv with the safety counts, SUMO's files under sumo/,
manifest.json), ``out/deploy_comparison.csv`` and ``out/deploy_summary.csv`` (every method
against the ground truth, ``deploy.compare``), the figures under ``out/plots/`` when the
caller passes its plotting function (the report layer's, ``report.deploy``), and
``out/deploy_manifest.json`` listing them all.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.deploy.calibrate import Calibration, calibration_record, fit_to_detectors
from macromicro_sumo.deploy.compare import compare_folders
from macromicro_sumo.deploy.floor_choice import resolve_floor
from macromicro_sumo.deploy.policy_batch import (
    action_std,
    policy_batch,
)
from macromicro_sumo.deploy.population import population_label, population_scenario
from macromicro_sumo.deploy.run import (
    DeployContext,
    Drive,
    load_context,
    run_method,
    write_method,
)
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation import section as section_eval
from macromicro_sumo.evaluation.idm_fit import (
    IdmParams,
    calibrate_idm,
)
from macromicro_sumo.evaluation.methods import BY_NAME
from macromicro_sumo.files import prepare_out_dir, staging_dir, write_csv, write_stage_manifest
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.checkpoint import load_policy, policy_file
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.physics import leader_length_m
from macromicro_sumo.truth.section import load_section_truth

MANIFEST = "deploy_manifest.json"
COMPARISON, SUMMARY = "deploy_comparison.csv", "deploy_summary.csv"
HISTORY = "calibration_history.csv"
PLOTS = "plots"
# ``oracle_redrawn``'s SUMO random streams: one for every lane instead of SUMO's default 64
# (one per lane modulo 64), so that every vehicle's draws change (63 would leave a network
# of fewer than 63 lanes with the truth's mapping: game/ramp repeated its truth exactly).
REDRAWN_RNG_STREAMS = 1
# (truth folder, method folders, comparison, plots folder) -> figures written: the report
# layer's ``report.deploy.make_deploy_plots``, passed in by the pipeline.
PlotDeploy = Callable[[Path, Mapping[str, Path], pd.DataFrame, Path], list[Path]]


@dataclass(frozen=True)
class DeployMethod:
    """One deployed method: ``how`` it drives (``learned``, ``idm``, ``defaults``,
    ``oracle``), what it is, the PPO objective of a learned one and the safety layer its
    commands go through ("": the scenario's ``deploy.safety``)."""

    name: str
    how: str
    what: str
    objective: str = ""
    safety: str = ""


def _what(name: str, fallback: str) -> str:
    return BY_NAME[name].what if name in BY_NAME else fallback


DEPLOY_METHODS: tuple[DeployMethod, ...] = (
    DeployMethod("policy", "learned", _what("policy", ""), "mix"),
    DeployMethod(
        "policy_no_safety",
        "learned",
        "the learned policy's speed commands applied exactly, without the safety layer",
        "mix",
        safety="none",
    ),
    DeployMethod("micro_only", "learned", _what("micro_only", ""), "micro_only"),
    DeployMethod("macro_only", "learned", _what("macro_only", ""), "macro_only"),
    DeployMethod("idm_calibrated", "idm", _what("idm_calibrated", "")),
    DeployMethod(
        "idm_detectors",
        "detectors",
        "IDM fitted to the training runs' detectors over whole SUMO runs (black box)",
    ),
    DeployMethod("sumo_default", "defaults", "SUMO's default model and parameters of each vClass"),
    DeployMethod("oracle", "oracle", "SUMO drives every vehicle with its true model"),
    DeployMethod(
        "oracle_redrawn",
        "oracle_redrawn",
        "the oracle with SUMO's own random draws (dawdling, lane changes) redrawn",
    ),
    DeployMethod(
        "oracle_population",
        "oracle_population",
        "oracle_redrawn with each driven vehicle's own parameters redrawn from its population",
    ),
)
METHOD = {m.name: m for m in DEPLOY_METHODS}


def idm_theta(p: IdmParams) -> dict[str, float]:
    """IDM parameters as SUMO's vType attributes (what ``Drive.theta`` takes)."""
    return {
        "accel": float(p.accel_mps2),
        "decel": float(p.decel_mps2),
        "tau": float(p.tau_s),
        "minGap": float(p.min_gap_m),
        "speedFactor": float(p.speed_factor),
        "delta": float(p.delta),
    }


def fit_idm(ctx: DeployContext) -> tuple[IdmParams, float]:
    """The IDM least-squares-fitted to the observed vehicles of the train and val runs, as
    the evaluation fits it; (parameters, RMSE of the fit [m/s^2])."""
    sc = ctx.sc
    truth = load_section_truth(ctx.truth_dir, sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    obs, acc = section_eval.micro_pairs(sc, truth, np.concatenate([splits["train"], splits["val"]]))
    return calibrate_idm(obs, acc, leader_length_m(sc.policy.observation, typical_length(truth)))


def policy_paths(policy_dir: Path | None, methods: list[str]) -> dict[str, Path]:
    """The checkpoints of the learned methods among ``methods``; a missing one is a
    one-line error naming the folder."""
    paths = {}
    for name in methods:
        m = METHOD[name]
        if m.how != "learned":
            continue
        if policy_dir is None:
            raise UserError(f"deploying {name} needs --policy (a policy folder or run folder)")
        path = policy_dir / policy_file(m.objective)
        if not path.is_file():
            raise UserError(
                f"{policy_dir}: no {path.name} for method {name}; pass a finished "
                "`macromicro run` folder or a policy folder (or leave the method out of "
                "deploy.methods)"
            )
        paths[name] = path
    return paths


def fixed_idm(ctx: DeployContext) -> dict[str, float]:
    """IDM parameters a detector fit holds: none (delta is SUMO's 4)."""
    return {}


def method_drive(
    name: str,
    sc: Any,
    agents: dict[str, Agent],
    idm: IdmParams | None,
    fitted: dict[str, float] | None = None,
) -> tuple[Drive, dict[str, Any]]:
    """How ``name`` drives, and what its manifest records of it (``fitted``: the
    detector-calibrated IDM's vType parameters)."""
    how = METHOD[name].how
    if how == "learned":
        safety = METHOD[name].safety or sc.deploy.safety
        floor = sc.deploy.safety_floor_share if safety == "sumo" else None
        std = action_std(agents[name]) if sc.deploy.action == "sample" else 0.0
        act = policy_batch(agents[name], sc.deploy.actor_dtype)
        drive = Drive(act=act, safety=safety, sample_std_mps2=std)
        record = {"safety": safety, "safety_floor_share": floor, "action": sc.deploy.action}
        # The family it drives with: the checkpoint's (policy.prior = "auto": the chosen one).
        record["prior"] = agents[name].prior
        record["action_std_mps2"] = std if sc.deploy.action == "sample" else None
        for key in ("safety_floor_on", "safety_brake"):
            record[key] = getattr(sc.deploy, key) if safety == "sumo" else None
        return drive, record
    if how == "idm":
        if idm is None:
            raise ValueError(f"{name}: needs the IDM fitted to the observed vehicles (fit_idm)")
        theta = idm_theta(idm)
        return Drive(theta=theta), {"theta": theta}
    if how == "detectors":
        # Drive(theta=None) drives the truth's own vTypes: the oracle under another name.
        if fitted is None:
            raise ValueError(f"{name}: needs the IDM fitted to the detectors (fit_to_detectors)")
        return Drive(theta=fitted), {"theta": fitted}
    if how == "defaults":
        return Drive(defaults=True), {}
    if how in ("oracle_redrawn", "oracle_population"):
        redraw = how == "oracle_population"
        drive = Drive(rng_streams=REDRAWN_RNG_STREAMS, redraw=redraw)
        return drive, {"rng_streams": REDRAWN_RNG_STREAMS, "redraw": redraw}
    return Drive(), {}


def deploy(
    sc: Any,
    data: Path | str,
    policy_dir: Path | str | None,
    out: Path | str,
    command: str = "",
    progress: bool = True,
    methods: list[str] | None = None,
    plots: PlotDeploy | None = None,
) -> dict[str, Any]:
    """Deploy ``methods`` (default ``deploy.methods``) on the held-out runs of the ground
    truth in ``data`` into ``out/<method>/``, compare them with it, and draw the figures
    with ``plots`` (none without); returns the stage manifest."""
    t0 = time.perf_counter()
    methods = list(methods or sc.deploy.methods)
    unknown = [m for m in methods if m not in METHOD]
    if unknown:
        raise UserError(f"unknown deploy method {unknown[0]!r}; accepted: {', '.join(METHOD)}")
    policy_dir = Path(policy_dir) if policy_dir is not None else None
    paths = policy_paths(policy_dir, methods)
    agents = {name: load_policy(p, sc, sc.deploy.speed_level) for name, p in paths.items()}
    ctx = load_context(sc, data)
    # With per-snapshot hidden sets the drivers drive the whole fleet (``population_scenario``).
    ctx.sc = population_scenario(ctx.sc)
    population = population_label(sc)
    torch.set_num_threads(1)
    idm, idm_rmse = fit_idm(ctx) if "idm_calibrated" in methods else (None, float("nan"))
    out = prepare_out_dir(out)
    timings, totals = {}, {}
    cal: Calibration | None = None
    fitted, record = None, None
    floors: dict[str, dict[str, Any]] = {}  # learned method -> its floor choice
    with staging_dir(out) as stage:
        if "idm_detectors" in methods:
            t1 = time.perf_counter()
            cal, fit_runs, start = fit_to_detectors(ctx, stage / "calibration", fixed_idm(ctx))
            shutil.rmtree(stage / "calibration", ignore_errors=True)
            fitted = {**cal.params, **fixed_idm(ctx)}
            record = calibration_record(cal, fit_runs, start)
            timings["idm_detectors_fit"] = round(time.perf_counter() - t1, 3)
        for name in tqdm(methods, desc="deploy", unit="method", disable=not progress):
            t1 = time.perf_counter()
            drive, extra = method_drive(name, sc, agents, idm, fitted)
            if name == "idm_detectors":
                extra["calibration"] = record
            # deploy.safety_floor_on = "auto": the floor chosen on training runs first
            drive, choice = resolve_floor(ctx, drive, stage / "floor_choice")
            if choice is not None:
                shutil.rmtree(stage / "floor_choice", ignore_errors=True)
                extra.update(safety_floor_on=drive.floor_on, safety_floor_choice=choice)
                floors[name] = choice
            folder = stage / name
            folder.mkdir()
            res = run_method(ctx, drive, folder)
            timings[name] = round(time.perf_counter() - t1, 3)
            manifest = build_manifest(sc, command, stage="deploy")
            manifest.update(
                method=name,
                what=METHOD[name].what,
                ground_truth=str(data),
                policy=str(paths.get(name, "")),
                held_out_runs=ctx.held_out,
                population=population,
                share=sc.deploy.share,
                vtype=sc.deploy.vtype,
                timings_s={"deploy": timings[name]},
                **extra,
            )
            if name == "idm_detectors":
                write_csv(cal.history, folder / HISTORY)
            totals[name] = write_method(ctx, res, folder, manifest)
        files = [f"{m}/manifest.json" for m in methods]
        dirs = {m: stage / m for m in methods}
        files += compare_into(Path(data), dirs, stage, plots, sc.deploy.compare_interval_s)
        if cal is not None:
            files.append(f"idm_detectors/{HISTORY}")
        manifest = build_manifest(sc, command, stage="deploy")
        manifest.update(
            ground_truth=str(data),
            policy_dir=str(policy_dir or ""),
            methods=methods,
            held_out_runs=ctx.held_out,
            population=population,
            safety=sc.deploy.safety,
            action=sc.deploy.action,
            idm_calibrated=(idm.as_dict() | {"fit_rmse_mps2": idm_rmse}) if idm else None,
            idm_detectors=record,
            safety_floor_choice=floors or None,
            totals=totals,
            timings_s={"deploy": round(time.perf_counter() - t0, 3), **timings},
        )
        write_stage_manifest(manifest, stage, MANIFEST, files)
    return manifest


def compare_into(
    truth_dir: Path,
    method_dirs: Mapping[str, Path],
    stage: Path,
    plots: PlotDeploy | None,
    compare_interval_s: float = 0.0,
) -> list[str]:
    """deploy_comparison.csv, deploy_summary.csv and the figures (``plots``) in ``stage``, at
    ``deploy.compare_interval_s``; their names relative to it (the stage's outputs)."""
    comparison, summary = compare_folders(truth_dir, method_dirs, compare_interval_s)
    write_csv(comparison, stage / COMPARISON)
    write_csv(summary, stage / SUMMARY)
    made = plots(truth_dir, method_dirs, comparison, stage / PLOTS) if plots else []
    return [COMPARISON, SUMMARY, *(f"{PLOTS}/{Path(p).name}" for p in made)]

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
  figures are the floor of the station-interval targets on this truth (docs/deploy.md,
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

import math
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.deploy.calibrate import Calibration, calibration_record, fit_to_detectors
from macromicro_sumo.deploy.compare import compare_folders
from macromicro_sumo.deploy.floor_choice import resolve_floor
from macromicro_sumo.deploy.population import ActionBatch, population_label, population_scenario
from macromicro_sumo.deploy.run import (
    DeployContext,
    Drive,
    load_context,
    run_method,
    write_method,
)
from macromicro_sumo.env.driver_speed import DriverSpeeds
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation import section as section_eval
from macromicro_sumo.evaluation.idm_fit import (
    GippsParams,
    IdmParams,
    calibrate_idm,
    gipps_policy_accel,
    idm_policy_accel,
)
from macromicro_sumo.evaluation.krauss_fit import KraussParams, krauss_policy_accel
from macromicro_sumo.evaluation.methods import BY_NAME
from macromicro_sumo.files import prepare_out_dir, staging_dir, write_csv, write_stage_manifest
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.checkpoint import load_policy, policy_file
from macromicro_sumo.policy.prior import PRIOR_KEYS
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.physics import leader_length_m
from macromicro_sumo.truth.section import load_section_truth

MANIFEST = "deploy_manifest.json"
COMPARISON, SUMMARY = "deploy_comparison.csv", "deploy_summary.csv"
HISTORY = "calibration_history.csv"
PLOTS = "plots"
# Rows per matrix product of the actor's numpy forward pass: larger products start
# OpenBLAS's threads, which on a loaded 2-core machine cost 1.8 ms at 500 rows instead of
# 0.3 ms (scripts/bench_deploy.py's sizes).
ACTOR_ROWS = 128
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


def actor_forward(agent: Agent) -> Callable[[np.ndarray], np.ndarray]:
    """The agent's actor as a numpy function of raw observations (n, D), float64, its
    weights read once: the actor's output before any prior or bound."""
    shift = agent.shift.detach().double().numpy()
    scale = agent.scale.detach().double().numpy()
    layers: list[tuple[np.ndarray, np.ndarray] | None] = []  # None: tanh
    for m in agent.actor:
        if isinstance(m, torch.nn.Linear):
            w = m.weight.detach().double().numpy().T.copy()
            layers.append((w, m.bias.detach().double().numpy().copy()))
        elif isinstance(m, torch.nn.Tanh):
            layers.append(None)
        else:
            raise TypeError(f"policy_batch: actor layer {type(m).__name__} not supported")

    last = max(i for i, layer in enumerate(layers) if layer is not None)
    # The hidden layers' outputs, kept between calls (grown as needed): written in place, the
    # same products and sums as fresh arrays, without a step's allocations.
    kept = [np.empty((0, 0 if layer is None else len(layer[1]))) for layer in layers]

    def forward(obs: np.ndarray) -> np.ndarray:
        x0 = np.subtract(obs, shift)
        np.divide(x0, scale, out=x0)
        n = len(x0)
        if n <= ACTOR_ROWS:  # one product per layer
            x = x0
            for i, layer in enumerate(layers):
                if layer is None:
                    np.tanh(x, out=x)
                    continue
                if i == last:  # a fresh output
                    x = np.matmul(x, layer[0])
                else:
                    if len(kept[i]) < n:
                        kept[i] = np.empty((max(n, ACTOR_ROWS // 2), len(layer[1])))
                    x = np.matmul(x, layer[0], out=kept[i][:n])
                np.add(x, layer[1], out=x)
            return x[:, 0]
        out = np.empty(n)
        for start in range(0, n, ACTOR_ROWS):
            x = x0[start : start + ACTOR_ROWS]
            for layer in layers:
                x = np.tanh(x, out=x) if layer is None else x @ layer[0] + layer[1]
            out[start : start + ACTOR_ROWS] = x[:, 0]
        return out

    return forward


def prior_forward(agent: Agent) -> Callable[[np.ndarray], np.ndarray] | None:
    """The agent's prior acceleration [m/s^2] as a numpy function of raw observations
    (``evaluation.idm_fit``'s twins of ``policy.prior``'s torch functions, which
    tests/policy/test_prior.py holds equal); None without a prior."""
    if agent.prior == "none":
        return None
    values = getattr(agent, f"{agent.prior}_prior").detach().double().tolist()
    p = dict(zip(PRIOR_KEYS[agent.prior], values, strict=True))
    if agent.prior == "idm":
        idm = IdmParams(**{k: v for k, v in p.items() if k != "veh_length_m"})
        return lambda obs: idm_policy_accel(obs, idm, p["veh_length_m"])
    fitted = {k: v for k, v in p.items() if k not in ("veh_length_m", "dt_s")}
    if agent.prior == "krauss":
        krauss = KraussParams(**fitted)
        return lambda obs: krauss_policy_accel(obs, krauss, p["veh_length_m"], p["dt_s"])
    gipps = GippsParams(**fitted)
    return lambda obs: gipps_policy_accel(obs, gipps, p["veh_length_m"], p["dt_s"])


def policy_batch(agent: Agent) -> ActionBatch:
    """The policy's deterministic mean action (``Agent.mean_action``) for every driven
    vehicle, one numpy call per step.

    Numpy, float64, the weights read once: torch's fixed cost per call (~0.1 ms for the
    actor, ~0.3 ms more for a prior's dozen small ops) was most of a step's policy time
    below 500 driven vehicles (``scripts/bench_deploy.py``). Equal to
    ``Agent.mean_action`` in float64 (tests/deploy/test_deploy_run.py)."""
    actor, prior = actor_forward(agent), prior_forward(agent)
    bound = float(agent.residual_bound) if prior is not None else math.inf

    def act(obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        if prior is None:
            return actor(obs)
        if bound <= 0.0:  # the fitted prior alone (an ablation)
            return prior(obs)
        out = actor(obs)
        if bound == 1.0:  # x / 1 and 1 y are x and y: the same values, two calls fewer
            out = np.tanh(out)
        elif math.isfinite(bound):
            out = bound * np.tanh(out / bound)
        return out + prior(obs)

    # policy.driver_speed: each driven vehicle's factor, set by its driver.
    q = agent.driver_speed
    act.driver_speeds = None if q is None else partial(DriverSpeeds, q.double().numpy())
    # The gap the policy stops at: its prior's minGap (``deploy.observe.observe_rows``).
    act.stop_gap_m = prior_stop_gap_m(agent)
    return act


def prior_stop_gap_m(agent: Agent) -> float | None:
    """The bumper gap [m] at which the agent's prior stops behind a standing leader, its
    fitted minGap (Krauss, Gipps; IDM's s0); None without a prior."""
    if agent.prior == "none":
        return None
    values = getattr(agent, f"{agent.prior}_prior").detach().double().tolist()
    return float(dict(zip(PRIOR_KEYS[agent.prior], values, strict=True))["min_gap_m"])


def action_std(agent: Agent) -> float:
    """The std [m/s^2] of the policy's Gaussian (state-independent, learned from the
    observed vehicles' likelihood): what ``deploy.action = "sample"`` draws with."""
    return float(agent.log_std.detach().double().exp().item())


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
        drive = Drive(act=policy_batch(agents[name]), safety=safety, sample_std_mps2=std)
        record = {"safety": safety, "safety_floor_share": floor, "action": sc.deploy.action}
        # The family it drives with: the checkpoint's (policy.prior = "auto": the chosen one).
        record["prior"] = agents[name].prior
        record["action_std_mps2"] = std if sc.deploy.action == "sample" else None
        for key in ("safety_floor_on", "safety_brake"):
            record[key] = getattr(sc.deploy, key) if safety == "sumo" else None
        return drive, record
    if how == "idm":
        theta = idm_theta(idm)
        return Drive(theta=theta), {"theta": theta}
    if how == "detectors":
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
    agents = {name: load_policy(p, sc) for name, p in paths.items()}
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

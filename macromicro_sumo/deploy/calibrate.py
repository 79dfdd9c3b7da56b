"""IDM calibrated to the detectors: a black-box fit over whole SUMO runs.

What corridor calibration studies do when only station data exist: choose the car-following
parameters that make a simulation of the demand reproduce the detectors' speeds and flows,
by a derivative-free search over whole runs (each evaluation is one deployment of the
candidate on the TRAINING runs; the held-out runs stay for the comparison). The search is
bounded Nelder-Mead in the unit box of the parameter ranges, started at the middle of the
ranges, and stops at a wall-clock budget or an evaluation count, keeping the best point
seen. The objective (``detector_loss``) is the root-mean-square relative speed error over
station-intervals plus the mean GEH of the flows divided by 5 (GEH < 5 is the usual
acceptance threshold, so both terms are ~1 where a fit is just acceptable).
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import minimize

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.deploy.compare import geh
from macromicro_sumo.deploy.run import DeployContext, Drive, run_method
from macromicro_sumo.errors import UserError

# IDM parameters the search varies, with the ranges it may use (SUMO's attribute names).
IDM_RANGES: dict[str, tuple[float, float]] = {
    "accel": (0.5, 3.0),  # [m/s^2] maximum acceleration a
    "decel": (1.0, 4.5),  # [m/s^2] comfortable deceleration b
    "tau": (0.6, 2.5),  # [s] desired time headway T
    "minGap": (0.5, 4.0),  # [m] jam distance s0
    "speedFactor": (0.8, 1.2),  # [-] desired speed / limit
}


@dataclass(frozen=True)
class Calibration:
    """The best parameters found, their loss, and every evaluation in order."""

    params: dict[str, float]
    loss: float
    history: pd.DataFrame  # eval, wall_s, loss, one column per parameter
    stopped_by: str  # "converged", "budget" or "evaluations"


class _Stop(Exception):
    """Raised inside the objective when the budget is spent (scipy then returns)."""


def detector_loss(truth: pd.DataFrame, sim: pd.DataFrame) -> float:
    """RMS relative speed error over station-intervals + mean flow GEH / 5.

    Both frames are in the ground truth's ``detectors.csv`` schema; rows are matched on
    (run, detector_id, begin_s). An interval with no speed on either side counts in the
    GEH only; a detector the candidate run lost counts as zero flow.
    """
    keys = ["run", "detector_id", "begin_s"]
    m = truth[[*keys, "flow_vph", "speed_mps"]].merge(
        sim[[*keys, "flow_vph", "speed_mps"]], on=keys, how="left", suffixes=("_t", "_s")
    )
    m["flow_vph_s"] = m["flow_vph_s"].fillna(0.0)
    g = geh(m["flow_vph_s"].to_numpy(), m["flow_vph_t"].to_numpy())
    g = g[np.isfinite(g)]  # a lane-area detector measures no flow: its speed counts only
    ok = (m["speed_mps_t"] > 0.1) & m["speed_mps_s"].notna()
    rel = (m.loc[ok, "speed_mps_s"] - m.loc[ok, "speed_mps_t"]) / m.loc[ok, "speed_mps_t"]
    speed_term = float(np.sqrt(np.mean(rel**2))) if ok.any() else 1.0
    return speed_term + float(np.mean(g)) / 5.0 if len(g) else math.inf


def loss_frame(det: pd.DataFrame) -> pd.DataFrame:
    """``detector_loss``'s columns from ``detectors.csv``, as written. SUMO's -1 (nobody
    passed) is no speed."""
    out = det[["run", "detector_id", "begin_s", "flow_vph", "speed_mps"]].copy()
    out["begin_s"] = out["begin_s"].round(3)
    out.loc[out["speed_mps"] < 0, "speed_mps"] = np.nan
    return out.reset_index(drop=True)


def calibrate(
    loss_of: Callable[[dict[str, float]], float],
    ranges: dict[str, tuple[float, float]] | None = None,
    budget_s: float = 300.0,
    max_evals: int = 200,
) -> Calibration:
    """Minimise ``loss_of(params)`` over the box ``ranges`` (default ``IDM_RANGES``).

    Deterministic: the start is the box's centre and Nelder-Mead draws nothing; a noisy
    ``loss_of`` should fix its own seeds (the deployment runs do: the same SUMO seeds).
    """
    ranges = dict(ranges or IDM_RANGES)
    names = list(ranges)
    lo = np.array([ranges[n][0] for n in names])
    hi = np.array([ranges[n][1] for n in names])
    rows: list[dict[str, float]] = []
    t0 = time.perf_counter()

    def params_of(u: np.ndarray) -> dict[str, float]:
        x = lo + np.clip(u, 0.0, 1.0) * (hi - lo)
        return {n: round(float(v), 4) for n, v in zip(names, x, strict=True)}

    def objective(u: np.ndarray) -> float:
        if len(rows) >= max_evals:
            raise _Stop("evaluations")
        if rows and time.perf_counter() - t0 >= budget_s:
            raise _Stop("budget")
        p = params_of(u)
        loss = float(loss_of(p))
        rows.append({"eval": len(rows), "wall_s": time.perf_counter() - t0, "loss": loss, **p})
        return loss if math.isfinite(loss) else 1e9

    stopped_by = "converged"
    # A first simplex of 20% of each range: whole runs are smooth in the parameters only
    # on that scale (SUMO's discrete steps make tiny moves look flat).
    u0 = np.full(len(names), 0.5)
    simplex = np.vstack([u0, u0 + 0.2 * np.eye(len(names))])
    try:
        minimize(
            objective,
            u0,
            method="Nelder-Mead",
            bounds=[(0.0, 1.0)] * len(names),
            options={"initial_simplex": simplex, "xatol": 0.01, "fatol": 1e-4, "maxfev": max_evals},
        )
    except _Stop as stop:
        stopped_by = str(stop)
    if stopped_by == "converged" and len(rows) >= max_evals:  # scipy's own maxfev stop
        stopped_by = "evaluations"
    history = pd.DataFrame(rows)
    best = history.loc[history["loss"].idxmin()]
    return Calibration({n: float(best[n]) for n in names}, float(best["loss"]), history, stopped_by)


def training_runs(ctx: DeployContext) -> list[int]:
    """The ground truth's training runs (never the held-out ones, never validation)."""
    sc = ctx.sc
    runs = np.sort(pd.read_csv(ctx.truth_dir / "runs.csv")["run"].unique())
    splits = split_runs(runs, sc.generator.held_out_fraction, sc.seed)
    if [int(r) for r in splits["held_out"]] != list(ctx.held_out):  # same split as the stage's
        raise UserError(
            f"{ctx.truth_dir}/runs.csv: its runs are not the ground truth's; re-simulate"
        )
    return [int(r) for r in splits["train"]]


def fit_to_detectors(
    ctx: DeployContext, scratch: Path, fixed: dict[str, float] | None = None
) -> tuple[Calibration, list[int], float]:
    """IDM fitted to the training runs' detectors by whole deployments of each candidate
    (``deploy.calibration_budget_s``, ``deploy.calibration_evals``); SUMO's files of each
    evaluation go to a scratch folder under ``scratch``, removed at once. ``fixed``: IDM
    parameters held, not fitted (the ring fleet's delta). Returns (the calibration, the
    runs fitted on, the start point's loss)."""
    dep = ctx.sc.deploy
    runs = training_runs(ctx)
    det = pd.read_csv(ctx.truth_dir / "detectors.csv")
    truth = loss_frame(det[det["run"].isin(runs)])
    scratch.mkdir(parents=True, exist_ok=True)

    def loss_of(params: dict[str, float]) -> float:
        folder = Path(tempfile.mkdtemp(prefix="eval_", dir=scratch))
        try:
            res = run_method(ctx, Drive(theta={**params, **(fixed or {})}), folder, runs=runs)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        return detector_loss(truth, loss_frame(res.detectors))

    cal = calibrate(loss_of, IDM_RANGES, dep.calibration_budget_s, dep.calibration_evals)
    return cal, runs, float(cal.history["loss"].iloc[0])


def calibration_record(cal: Calibration, runs: list[int], start_loss: float) -> dict[str, Any]:
    """What a manifest records of a detector calibration."""
    return {
        "params": cal.params,
        "loss": cal.loss,
        "start_loss": start_loss,
        "evaluations": len(cal.history),
        "stopped_by": cal.stopped_by,
        "wall_s": round(float(cal.history["wall_s"].iloc[-1]), 3),
        "training_runs": runs,
        "ranges": {k: list(v) for k, v in IDM_RANGES.items()},
    }

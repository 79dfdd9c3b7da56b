"""Classify a deployment's emergency brakings (issue 17): deploy a finished run's method
on chosen runs as ``scripts/deploy_runs.py`` does and, for every vehicle-step the driver
counts as an emergency braking (``deploy.drivers``: braking harder than its demand vType's
decel by more than 0.01 m/s^2), say who braked, where, and what asked it, from the
commands of the step before (the one SUMO applied):

* ``policy``: a commanded vehicle whose action (after the bounds and
  ``deploy.command_brake``) braked beyond its decel;
* ``merge_yield``: its merge yield's cap (SUMO's cooperative slow-down, ``deploy.merge_yield``);
* ``keep_right``: another cap before the layer (``deploy.keep_right``);
* ``safety``: the safety layer's cap (the safe speed behind what is ahead, a driven
  leader's command), the layer braking beyond the decel: a real emergency;
* ``sumo_applied``: commanded within decel, but SUMO braked harder (right of way, a red
  light under speed mode 24);
* ``merging``: handed over to SUMO's model to leave its lane (``deploy.merge``);
* ``released``: handed back to SUMO's model within the last 10 steps (leaving the
  section), SUMO's own braking;
* ``instrumented``: outside the driven population (the observed vehicles SUMO drives);
* ``off_section`` / ``sumo``: another vehicle SUMO drives, off the section or not.

``cut_in``: what the vehicle saw ahead was more than 5 m nearer than the step before's
could have come at its speed (a new leader: one that changed lanes in front of it, its own
lane change, or one come into view); ``last_stop_ahead``: what it saw ahead was a lane end
or a red light; ``yield_steps``: its merge yield on its
last commanded steps ("y1010": on, off, on, off).

Writes ``--out``/brakings.csv (one row per emergency braking) and prints the counts by
class, vType and edge. Diagnostic hooks wrap the driver's methods in this process only.

    .venv/bin/python scripts/classify_brakings.py SCENARIO.toml RUN_DIR --out DIR \\
        [--runs 0 1] [--set deploy.command_brake=decel deploy.merge_reach=occupation]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from deploy_runs import detector_theta, prepared

from macromicro_sumo.deploy import drivers
from macromicro_sumo.deploy.floor_choice import resolve_floor
from macromicro_sumo.deploy.observe import STOP_DECEL_MPS2
from macromicro_sumo.deploy.run import run_method
from macromicro_sumo.deploy.safety import command_brake
from macromicro_sumo.deploy.stage import fit_idm, method_drive
from macromicro_sumo.errors import UserError
from macromicro_sumo.sumo.simulation import Simulation

TOL_MPS2 = drivers.BRAKING_TOLERANCE_MPS2  # what the driver counts as beyond decel
RECENT_STEPS = 10


class Recorder:
    """Per driver step, each commanded vehicle's speed, action's command, caps and final
    command; the steps vehicles were released at; the emergency brakings classified."""

    def __init__(self) -> None:
        self.step = 0
        self.run = -1
        self.pending: dict[str, np.ndarray] | None = None
        self.yield_cap: np.ndarray | None = None
        self.last: dict[str, tuple[int, dict[str, float]]] = {}
        self.prev: dict[str, tuple[int, dict[str, float]]] = {}
        self.released: dict[str, int] = {}
        # Per vehicle, its last commanded steps' merge-yield flags (1: yielding), newest last.
        self.yielding: dict[str, str] = {}
        self.rows: list[dict] = []


REC = Recorder()


def install(sc) -> Callable[[], None]:
    """Wrap the driver's command rule, its merge yield, its braking count and SUMO's
    speed setters, recording what each step's commands were made of (into ``REC``, cleared
    here). Returns the undo: every wrapped name back to what it was."""
    saved = [
        (drivers, "speed_commands", drivers.speed_commands),
        (drivers.SectionSpeedDriver, "yields", drivers.SectionSpeedDriver.yields),
        (Simulation, "set_speeds", Simulation.set_speeds),
        (Simulation, "release_speeds", Simulation.release_speeds),
        (drivers.SectionDriver, "count_brakings", drivers.SectionDriver.count_brakings),
    ]
    REC.__init__()
    orig_cmd = drivers.speed_commands
    a_min, _ = sc.bounds.accel_mps2
    dt = sc.simulation.step_length_s

    def speed_commands(sc_, act, safety, stats, obs, layer, cap=None, *args, **kw):
        got: dict[str, np.ndarray] = {}

        def act2(o: np.ndarray) -> np.ndarray:
            got["a"] = np.asarray(act(o), dtype=float)
            return got["a"]

        cmd = orig_cmd(sc_, act2, safety, stats, obs, layer, cap, *args, **kw)
        v = obs[:, 0]
        n = len(v)
        if safety == "sumo":
            gap, decel, lead_decel, lead = layer()
        else:
            gap, decel, lead = np.full(n, np.nan), np.full(n, np.inf), np.full(n, -1)
            lead_decel = np.full(n, np.nan)
        lo = command_brake(a_min, decel, sc_.deploy.command_brake)
        a = np.maximum(got["a"], lo)
        yc = REC.yield_cap if REC.yield_cap is not None else np.full(n, np.inf)
        REC.pending = {
            "v": v.copy(),
            "policy": np.maximum(v + a * dt, 0.0),
            "yield": np.asarray(yc, dtype=float) * np.ones(n),
            "cap": np.full(n, np.inf) if cap is None else np.asarray(cap, dtype=float) * np.ones(n),
            "cmd": np.asarray(cmd, dtype=float).copy(),
            "gap": np.asarray(gap, dtype=float).copy(),
            "lead_v": obs[:, 0] - obs[:, 3],
            # What it sees ahead stands for good: a lane end or a red light (observe's
            # STOP_DECEL_MPS2 as its decel), not a vehicle.
            "stop_ahead": (np.asarray(lead_decel, dtype=float) >= STOP_DECEL_MPS2).astype(float),
            "lead_driven": (np.asarray(lead) >= 0).astype(float),
        }
        REC.yield_cap = None
        return cmd

    drivers.speed_commands = speed_commands
    orig_yields = drivers.SectionSpeedDriver.yields

    def yields(self, *args, **kw):
        out = orig_yields(self, *args, **kw)
        REC.yield_cap = np.asarray(out, dtype=float).copy()
        return out

    drivers.SectionSpeedDriver.yields = yields
    orig_set = Simulation.set_speeds

    def set_speeds(self, vids, speeds):
        p = REC.pending
        if p is not None and len(p["cmd"]) == len(vids):
            for i, vid in enumerate(vids):
                if vid in REC.last:
                    REC.prev[vid] = REC.last[vid]
                REC.last[vid] = (REC.step, {k: float(x[i]) for k, x in p.items()})
                flag = "1" if np.isfinite(p["yield"][i]) else "0"
                REC.yielding[vid] = (REC.yielding.get(vid, "") + flag)[-8:]
        REC.pending = None
        return orig_set(self, vids, speeds)

    Simulation.set_speeds = set_speeds
    orig_release = Simulation.release_speeds

    def release_speeds(self, vids):
        for vid in vids:
            REC.released[vid] = REC.step
        return orig_release(self, vids)

    Simulation.release_speeds = release_speeds
    orig_count = drivers.SectionDriver.count_brakings

    def count_brakings(self, st):
        if self.steps == 1:  # a new run's driver
            REC.run += 1
            REC.last.clear()
            REC.prev.clear()
            REC.released.clear()
            REC.yielding.clear()
        REC.step = self.steps
        orig_count(self, st)
        decel = np.fromiter(map(self.decel_of.get, st.ids, [np.inf] * len(st.ids)), float)
        for i in np.flatnonzero(st.accel_mps2 < -decel - TOL_MPS2).tolist():
            vid = st.ids[i]
            REC.rows.append(classify(vid, st, i, decel[i], self, dt))

    drivers.SectionDriver.count_brakings = count_brakings

    def undo() -> None:
        for owner, name, value in saved:
            setattr(owner, name, value)

    return undo


def classify(vid: str, st, i: int, decel: float, driver, dt: float) -> dict:
    """One emergency braking's row: who, where, what asked it."""
    row = {
        "run": REC.run,
        "step": REC.step,
        "vehicle_id": vid,
        "vtype": driver.types.get(vid, ""),
        "decel_mps2": decel,
        "accel_mps2": float(st.accel_mps2[i]),
        "speed_mps": float(st.speed_mps[i]),
        "lane": st.lanes[i],
        "pos_m": float(st.pos_m[i]),
    }
    step, rec = REC.last.get(vid, (-1, None))
    if rec is not None and step == REC.step - 1:
        least = max(rec["v"] - decel * dt, 0.0) - TOL_MPS2 * dt
        if rec["policy"] < least:
            what = "policy"
        elif rec["yield"] < least:
            what = "merge_yield"
        elif rec["cap"] < least:
            what = "keep_right"
        elif rec["cmd"] < least:
            what = "safety"
        else:
            what = "sumo_applied"
        row.update({f"last_{k}": x for k, x in rec.items()})
        # Its merge yield on the last commanded steps, oldest first ("y1010": on, off, ...).
        row["yield_steps"] = "y" + REC.yielding.get(vid, "")
        pstep, prev = REC.prev.get(vid, (-1, None))
        # What is ahead more than 5 m nearer than the step before's, moved on at its speed,
        # could have come: a new leader (one that cut in, or its own lane change), or one
        # that came into view from beyond NO_LEADER_GAP_M.
        row["cut_in"] = bool(
            prev is not None
            and pstep == step - 1
            and rec["gap"] < prev["gap"] - (prev["v"] - prev["lead_v"]) * dt - 5.0
        )
        row["prev_gap"] = np.nan if prev is None else prev["gap"]
    elif vid in getattr(driver, "merging", ()):
        what = "merging"  # handed over to SUMO's model to leave its lane
    elif REC.step - REC.released.get(vid, -(10**9)) <= RECENT_STEPS:
        what = "released"
    elif vid not in driver.population:
        what = "instrumented"
    elif st.lanes[i] not in driver.section.lanes:
        what = "off_section"
    else:
        what = "sumo"
    row["what"] = what
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", type=Path)
    p.add_argument("run", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--method", default="policy")
    p.add_argument("--runs", nargs="+", type=int, default=None)
    p.add_argument("--set", nargs="*", default=[], dest="changes")
    o = p.parse_args(argv)
    try:
        sc, ctx, runs, agents = prepared(o.scenario, o.run, o.changes, [o.method], o.runs, o.out)
    except UserError as e:
        print(f"classify_brakings: {e}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    try:  # the fits the deploy stage drove idm_calibrated / idm_detectors with
        idm = fit_idm(ctx)[0] if o.method == "idm_calibrated" else None
        fitted = detector_theta(o.run) if o.method == "idm_detectors" else None
    except UserError as e:
        print(f"classify_brakings: {e}", file=sys.stderr)
        return 2
    drive, _ = method_drive(o.method, sc, agents, idm, fitted)
    o.out.mkdir(parents=True, exist_ok=True)
    drive, _ = resolve_floor(ctx, drive, o.out / "floor_choice")
    undo = install(ctx.sc)  # after the floor's choice: only the runs classified are recorded
    try:
        res = run_method(ctx, drive, o.out / o.method, runs=runs)
    finally:
        undo()
    df = pd.DataFrame(REC.rows)
    df.to_csv(o.out / "brakings.csv", index=False)
    print(res.runs[["run", "collisions", "teleports", "emergency_brakings"]].to_string(index=False))
    if df.empty:
        print("no emergency brakings")
        return 0
    df["edge"] = df["lane"].str.rsplit("_", n=1).str[0]
    print(f"{len(df)} emergency brakings")
    for col in ("what", "vtype", "edge"):
        print(df.groupby(col).size().sort_values(ascending=False).head(12).to_string(), "\n")
    print(pd.crosstab(df["vtype"], df["what"]).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

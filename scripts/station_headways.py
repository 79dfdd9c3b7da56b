"""Headways by the follower's vType where vehicles pass a point of a one-lane stretch: from
trajectories.csv files (a ground truth's, or a deployment's with ``deploy.fcd_s`` covering
the window), each vehicle's passage of ``--arc`` (linear between its samples), the headway
to the vehicle that passed before it in the same run, kept where it passes in
[``--from``, ``--to``) s. Prints per file: passages a run, mean headway, the mean by the
follower's vType, the mean passing speed. Issue 17 (drawn 501's queue discharge at 1125 m,
docs/deploy-log.md, stop 42, hQ):

    .venv/bin/python scripts/station_headways.py --arc 1125 --from 330 --to 600 \\
        truth=RUN/ground_truth/trajectories.csv policy=DEPLOY/policy/trajectories.csv

Only where the point has one lane: on several lanes the vehicle passing before may be on
another one.

``--start-lags SIGNALS`` (the ground truth's signals.csv) measures instead how a queue
standing at the stop line ``--arc`` starts at each green (issue 17, drawn arterial 528,
docs/deploy-log.md stop 43): the vehicles standing (< ``STANDING_MPS``) within ``REACH_M``
upstream of the line as the light turns green, in queue order; each one's start (its
first sample faster than ``MOVING_MPS``) after the green, and its lag behind the start of
the vehicle ahead of it in the queue (the head: behind the green); a vehicle that has not
moved by the window's end (or ``START_WITHIN_S``) ends its queue. Several ``--arc`` pool
their stop lines. Prints per file the queues, the mean lag by queue position and when the
5th, 10th and 20th vehicles start:

    .venv/bin/python scripts/station_headways.py --arc 195.8 --arc 398.8 --arc 601.8 \\
        --arc 804.8 --start-lags RUN/ground_truth/signals.csv \\
        truth=RUN/ground_truth/trajectories.csv policy=DEPLOY/policy/trajectories.csv

``--yellow-onsets SIGNALS`` (the same arguments) measures what the vehicles do at each
yellow onset of the lines (``deploy`` stop 44, hF44): each one moving (> ``MOVING_MPS``)
within ``REACH_M`` upstream of a line at the last sample before the yellow, whether it could
brake before the line at its decel (SUMO's Euler brakeGap at most its distance less SUMO's
1 m jmStoplineGap; decel ``YELLOW_DECEL_MPS2``, a vType's own with ``--decel VTYPE=B``) and
whether it crossed the line before the red; the onsets in [``--from``, ``--to``). Prints per
file the onsets, the vehicles that could brake and those of them that crossed on the
yellow, and the same of those that could not.

``--greens SIGNALS`` (the same arguments) measures the discharge of each green at the lines
(issue 17, drawn arterials, stop 45): per green (its onset to the red after its yellow) and
lane, the vehicles crossing the line, when the 1st, 4th and 12th crossed after the onset,
and the saturation headway (t_12 - t_4) / 8 where at least 12 crossed; greens whose onset
is in [``--from``, ``--to``). Prints per file the crossings per green and lane (lanes that
carried any), t_1 / t_4 / t_12 and the saturation headway (the greens with 12).

``--pull-away SIGNALS`` (the same arguments) measures how each queue leaves its green
(issue 17, drawn 1706, stop 50, hA50): ``--start-lags``' queues, and per queue position
(the first ``PULL_POSITIONS``) the mean speed ``PULL_TIMES_S`` after the green and when it
crosses the line and ``PULL_PAST_M`` past it [s after the green]; the trajectories must
cover the run (``deploy.fcd_s``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

COLUMNS = ["run", "time_s", "vehicle_id", "vtype", "arc_m", "speed_mps"]


def passages(traj: pd.DataFrame, arc_m: float) -> pd.DataFrame:
    """Each vehicle's first passage of ``arc_m``: run, vehicle, vType, time [s] and speed
    [m/s] (linear between the samples around it), in time order per run."""
    traj = traj.sort_values(["run", "vehicle_id", "time_s"])
    a = traj["arc_m"].to_numpy()
    same = (traj["run"].to_numpy()[1:] == traj["run"].to_numpy()[:-1]) & (
        traj["vehicle_id"].to_numpy()[1:] == traj["vehicle_id"].to_numpy()[:-1]
    )
    i = np.flatnonzero(same & (a[:-1] < arc_m) & (a[1:] >= arc_m))
    f = (arc_m - a[i]) / (a[i + 1] - a[i])
    t, v = traj["time_s"].to_numpy(), traj["speed_mps"].to_numpy()
    out = pd.DataFrame(
        {
            "run": traj["run"].to_numpy()[i],
            "vehicle_id": traj["vehicle_id"].to_numpy()[i],
            "vtype": traj["vtype"].to_numpy()[i],
            "time_s": t[i] + f * (t[i + 1] - t[i]),
            "speed_mps": v[i] + f * (v[i + 1] - v[i]),
        }
    )
    out = out.drop_duplicates(["run", "vehicle_id"])  # a vehicle's first passage
    return out.sort_values(["run", "time_s"]).reset_index(drop=True)


def headways(p: pd.DataFrame, t0_s: float, t1_s: float) -> pd.DataFrame:
    """``passages`` with each one's headway [s] to the passage before it in its run, those
    in [t0_s, t1_s) that have one."""
    p = p.assign(headway_s=p.groupby("run")["time_s"].diff())
    keep = (p["time_s"] >= t0_s) & (p["time_s"] < t1_s) & p["headway_s"].notna()
    return p[keep]


# --start-lags: a vehicle stands below this speed, moves above the other [m/s]; the queue
# counted reaches this far upstream of the line [m] (a block of drawn arterial 528: 203 m);
# a queued vehicle that has not moved this long after the green ends its queue [s].
STANDING_MPS = 0.1
MOVING_MPS = 0.5
REACH_M = 200.0
START_WITHIN_S = 40.0
# Queue positions grouped (first, last) for the printed means.
POSITIONS = ((1, 1), (2, 4), (5, 10), (11, 10_000))


def green_onsets(signals: pd.DataFrame, arc_m: float) -> pd.DataFrame:
    """run, time_s of each switch to green (state G or g after another state) of the links
    whose stop line is at ``arc_m`` (within 0.5 m) in a signals.csv frame."""
    at = signals[(signals["arc_m"] - arc_m).abs() <= 0.5].sort_values(["run", "time_s"])
    at = at.drop_duplicates(["run", "time_s"])  # one row per step (the same signal's links)
    green = at["state"].isin(["G", "g"]).to_numpy()
    same_run = at["run"].to_numpy()[1:] == at["run"].to_numpy()[:-1]
    onset = np.concatenate([[False], green[1:] & ~green[:-1] & same_run])
    return at.loc[onset, ["run", "time_s"]].reset_index(drop=True)


def start_lags(traj: pd.DataFrame, arc_m: float, onsets: pd.DataFrame) -> pd.DataFrame:
    """One row per queued vehicle and green (``green_onsets``) the trajectories cover: run,
    green time, queue position (1: the head), vehicle, vType, start [s after the green] and
    lag [s] behind the start of the one ahead (the head's: its start)."""
    rows = []
    for run, tr in traj.groupby("run"):
        times = np.sort(tr["time_s"].unique())
        for g in onsets.loc[onsets["run"] == run, "time_s"]:
            before = times[times < g]
            if not len(before) or g >= times[-1]:
                continue  # the window does not hold this green's start
            snap = tr[tr["time_s"] == before[-1]]
            queue = snap[
                (snap["arc_m"] < arc_m)
                & (snap["arc_m"] > arc_m - REACH_M)
                & (snap["speed_mps"] < STANDING_MPS)
            ].sort_values("arc_m", ascending=False)
            after = tr[(tr["time_s"] >= g) & (tr["time_s"] <= g + START_WITHIN_S)]
            first = after[after["speed_mps"] > MOVING_MPS].groupby("vehicle_id")["time_s"].min()
            ahead = 0.0
            for k, r in enumerate(queue.itertuples(index=False), 1):
                if r.vehicle_id not in first.index:
                    break  # it did not start: the queue behind it is held by it
                start = float(first[r.vehicle_id]) - g
                rows.append((run, g, k, r.vehicle_id, r.vtype, start, start - ahead))
                ahead = start
    cols = ["run", "green_s", "position", "vehicle_id", "vtype", "start_s", "lag_s"]
    return pd.DataFrame(rows, columns=cols)


# --yellow-onsets: the decel a vType brakes at where ``--decel`` names none (SUMO's Krauss
# passenger car's) [m/s^2]; a yellow line's jmStoplineGap [m], SUMO's default.
YELLOW_DECEL_MPS2 = 4.5
STOPLINE_GAP_M = 1.0


def yellow_onsets(signals: pd.DataFrame, arc_m: float) -> pd.DataFrame:
    """run, time_s of each switch from green to yellow (G or g, then y or Y) and the time
    of the red after it (red_s; inf: the yellow outlasts the file) of the links whose stop
    line is at ``arc_m`` (within 0.5 m) in a signals.csv frame."""
    at = signals[(signals["arc_m"] - arc_m).abs() <= 0.5].sort_values(["run", "time_s"])
    at = at.drop_duplicates(["run", "time_s"])
    rows = []
    for run, g in at.groupby("run"):
        st, t = g["state"].to_numpy(), g["time_s"].to_numpy()
        yellow = np.isin(st, ["y", "Y"])
        for i in np.flatnonzero(yellow[1:] & np.isin(st[:-1], ["G", "g"])) + 1:
            after = np.flatnonzero(~yellow[i:])
            rows.append((run, t[i], t[i + after[0]] if after.size else np.inf))
    return pd.DataFrame(rows, columns=["run", "time_s", "red_s"])


def euler_brake_gap(v: np.ndarray, b: np.ndarray, dt_s: float) -> np.ndarray:
    """SUMO's brakeGap [m] in Euler steps of ``dt_s`` (``road.physics.brake_gap``)."""
    steps = np.floor(v / (b * dt_s))
    return dt_s * (steps * v - b * dt_s * steps * (steps + 1.0) / 2.0)


def at_yellow(
    traj: pd.DataFrame, arc_m: float, onsets: pd.DataFrame, decel: dict[str, float]
) -> pd.DataFrame:
    """One row per vehicle moving within ``REACH_M`` upstream of the line at the last sample
    before a yellow onset (``yellow_onsets``) the trajectories cover: run, onset, vehicle,
    distance [m], speed [m/s], whether it could brake before the line at its decel
    (``decel``: by vType, else ``YELLOW_DECEL_MPS2``) and whether it crossed before the red."""
    rows = []
    for run, tr in traj.groupby("run"):
        times = np.sort(tr["time_s"].unique())
        dt = float(np.median(np.diff(times))) if len(times) > 1 else 0.5
        for y, red in onsets.loc[onsets["run"] == run, ["time_s", "red_s"]].itertuples(False):
            before = times[times < y]
            if not len(before) or y >= times[-1]:
                continue
            snap = tr[tr["time_s"] == before[-1]]
            near = snap[
                (snap["arc_m"] < arc_m)
                & (snap["arc_m"] > arc_m - REACH_M)
                & (snap["speed_mps"] > MOVING_MPS)
            ]
            past = tr[(tr["time_s"] >= y) & (tr["time_s"] < red) & (tr["arc_m"] >= arc_m)]
            crossed = set(past["vehicle_id"])
            for r in near.itertuples(index=False):
                d, b = arc_m - r.arc_m, decel.get(r.vtype, YELLOW_DECEL_MPS2)
                can = float(euler_brake_gap(np.float64(r.speed_mps), b, dt)) <= d - STOPLINE_GAP_M
                rows.append((run, y, r.vehicle_id, d, r.speed_mps, can, r.vehicle_id in crossed))
    cols = ["run", "yellow_s", "vehicle_id", "distance_m", "speed_mps", "can_brake", "crossed"]
    return pd.DataFrame(rows, columns=cols)


def yellow_summary(cars: pd.DataFrame) -> dict[str, float]:
    """Onsets, and per could / could not brake: vehicles and those that crossed on the yellow."""
    keys = [k for k in ("run", "yellow_s", "arc_m") if k in cars]
    out = {"onsets": float(cars.groupby(keys).ngroups)}
    for can, name in ((True, "could_brake"), (False, "could_not")):
        sel = cars[cars["can_brake"] == can]
        out[name] = float(len(sel))
        out[f"{name}_crossed"] = float(sel["crossed"].sum())
    return out


def lag_summary(lags: pd.DataFrame) -> dict[str, float]:
    """Queues (greens with a queue), mean lag [s] per ``POSITIONS`` group, and the mean start
    [s after the green] of the 5th, 10th and 20th queued vehicle."""
    keys = [k for k in ("run", "green_s", "arc_m") if k in lags]  # arc_m: lines pooled
    out = {"queues": float(lags.groupby(keys).ngroups)}
    for lo, hi in POSITIONS:
        name = f"lag_{lo}" if hi == lo else f"lag_{lo}+" if hi >= 10_000 else f"lag_{lo}-{hi}"
        out[name] = lags.loc[lags["position"].between(lo, hi), "lag_s"].mean()
    for k in (5, 10, 20):
        out[f"start_{k}th_s"] = lags.loc[lags["position"] == k, "start_s"].mean()
    return out


# --greens: the crossing after the onset whose time starts and ends the saturation headway
# (1-based; hA43's tools/greens.py: the 4th to the 12th, past the start-up loss); the
# crossings whose headway behind the one before is reported alone (the 2nd to the 6th: the
# start-up of a standing queue, issue 17, arterials 1164 / 1407, stop 48).
SAT_FIRST, SAT_LAST = 4, 12
HEADWAYS = (2, 3, 4, 5, 6)


def green_windows(signals: pd.DataFrame, arc_m: float) -> pd.DataFrame:
    """run, time_s of each green onset (``green_onsets``) of the line at ``arc_m`` and the
    time of the first step after it neither green nor yellow (red_s; inf: the file ends)."""
    at = signals[(signals["arc_m"] - arc_m).abs() <= 0.5].sort_values(["run", "time_s"])
    at = at.drop_duplicates(["run", "time_s"])
    rows = []
    for run, g in at.groupby("run"):
        st, t = g["state"].to_numpy(), g["time_s"].to_numpy()
        green, open_ = np.isin(st, ["G", "g"]), np.isin(st, ["G", "g", "y", "Y"])
        for i in np.flatnonzero(green[1:] & ~green[:-1]) + 1:
            after = np.flatnonzero(~open_[i:])
            rows.append((run, t[i], t[i + after[0]] if after.size else np.inf))
    return pd.DataFrame(rows, columns=["run", "time_s", "red_s"])


def green_discharge(traj: pd.DataFrame, arc_m: float, windows: pd.DataFrame) -> pd.DataFrame:
    """One row per green (``green_windows``) the trajectories cover and lane that a vehicle
    crossed the line at ``arc_m`` on during it (its lane the sample before): run, green,
    lane, crossings, t_1, t_4, t_12 [s after the onset] (nan: fewer crossed) and the
    saturation headway (t_12 - t_4) / 8 [s]. A lane nothing crossed on has no row."""
    traj = traj.sort_values(["run", "vehicle_id", "time_s"])
    a = traj["arc_m"].to_numpy()
    same = (traj["run"].to_numpy()[1:] == traj["run"].to_numpy()[:-1]) & (
        traj["vehicle_id"].to_numpy()[1:] == traj["vehicle_id"].to_numpy()[:-1]
    )
    i = np.flatnonzero(same & (a[:-1] < arc_m) & (a[1:] >= arc_m))
    t = traj["time_s"].to_numpy()
    cross = pd.DataFrame(
        {
            "run": traj["run"].to_numpy()[i],
            "lane": traj["lane_index"].to_numpy()[i],
            "time_s": t[i] + (arc_m - a[i]) / (a[i + 1] - a[i]) * (t[i + 1] - t[i]),
        }
    )
    rows = []
    for run, cr in cross.groupby("run"):
        times = traj.loc[traj["run"] == run, "time_s"]
        t_lo, t_hi = times.min(), times.max()
        for g, red in windows.loc[windows["run"] == run, ["time_s", "red_s"]].itertuples(False):
            if g < t_lo or red > t_hi:
                continue  # the trajectories do not cover this green
            inside = cr[(cr["time_s"] >= g) & (cr["time_s"] < red)]
            for lane, c in inside.groupby("lane"):
                c = np.sort(c["time_s"].to_numpy()) - g
                at = [c[k - 1] if len(c) >= k else np.nan for k in (1, SAT_FIRST, SAT_LAST)]
                sat = (at[2] - at[1]) / (SAT_LAST - SAT_FIRST)
                first = [c[k - 1] - c[k - 2] if len(c) >= k else np.nan for k in HEADWAYS]
                rows.append((run, g, int(lane), len(c), *at, sat, *first))
    cols = ["run", "green_s", "lane", "crossings", "t_1_s", "t_4_s", "t_12_s", "sat_headway_s"]
    return pd.DataFrame(rows, columns=cols + [f"h_{k}_s" for k in HEADWAYS])


# --pull-away: the queue positions, the times after the green [s] and the distances past the
# line [m] it reports.
PULL_POSITIONS = 5
PULL_TIMES_S = (0.0, 2.0, 4.0, 6.0, 8.0)
PULL_PAST_M = (0.0, 50.0, 100.0)


def pull_away(traj: pd.DataFrame, arc_m: float, onsets: pd.DataFrame) -> pd.DataFrame:
    """One row per queued vehicle (``start_lags``) in the first ``PULL_POSITIONS``: its
    position, speed [m/s] ``PULL_TIMES_S`` after the green (v_T) and when [s after the
    green] it passes the line and ``PULL_PAST_M`` beyond (x_D), linear between its
    samples (NaN: beyond its samples)."""
    queued = start_lags(traj, arc_m, onsets)
    queued = queued[queued["position"] <= PULL_POSITIONS]
    cars = traj.set_index(["run", "vehicle_id"]).sort_index()
    rows = []
    for r in queued.itertuples(index=False):
        car = cars.loc[(r.run, r.vehicle_id)].sort_values("time_s")
        t = car["time_s"].to_numpy() - r.green_s
        v = np.interp(PULL_TIMES_S, t, car["speed_mps"].to_numpy(), right=np.nan)
        x = np.interp(np.add(arc_m, PULL_PAST_M), car["arc_m"].to_numpy(), t, right=np.nan)
        rows.append((r.position, *v, *x))
    cols = [f"v_{t:g}s" for t in PULL_TIMES_S] + [f"x_{d:g}m" for d in PULL_PAST_M]
    return pd.DataFrame(rows, columns=["position", *cols])


def green_summary(d: pd.DataFrame) -> dict[str, float]:
    """Green-lanes, crossings per green and lane, mean t_1 / t_4 / t_12 and saturation
    headway (the green-lanes with ``SAT_LAST`` crossings), and how many had them; the mean
    t_1 and headways h_2 .. h_6 of the green-lanes with 6 crossings (``HEADWAYS``: the
    queue's start-up), and how many had them."""
    out = {"green_lanes": float(len(d)), "crossings": d["crossings"].mean()}
    full = d[d["crossings"] >= SAT_LAST]
    out |= {k: full[k].mean() for k in ("t_1_s", "t_4_s", "t_12_s", "sat_headway_s")}
    out |= {"with_12": float(len(full))}
    six = d[d["crossings"] >= HEADWAYS[-1]]
    out |= {"t_1_of6_s": six["t_1_s"].mean()}
    out |= {f"h_{k}_s": six[f"h_{k}_s"].mean() for k in HEADWAYS}
    return out | {"with_6": float(len(six))}


def summary(h: pd.DataFrame, runs: int) -> dict[str, float]:
    """Passages a run, mean headway [s] overall and by vType, mean passing speed [m/s]."""
    out = {"passages_per_run": len(h) / max(runs, 1), "headway_s": h["headway_s"].mean()}
    out |= {f"headway_{k}_s": x for k, x in h.groupby("vtype")["headway_s"].mean().items()}
    return out | {"speed_mps": h["speed_mps"].mean()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--arc",
        type=float,
        action="append",
        required=True,
        help="the point's arc [m]; with --start-lags one --arc per stop line",
    )
    ap.add_argument("--from", dest="t0", type=float, default=0.0, help="window start [s]")
    ap.add_argument("--to", dest="t1", type=float, default=np.inf, help="window end [s]")
    ap.add_argument(
        "--start-lags",
        metavar="SIGNALS_CSV",
        help="the truth's signals.csv: queue start-up lags at each green of the stop line --arc",
    )
    ap.add_argument(
        "--yellow-onsets",
        metavar="SIGNALS_CSV",
        help="the truth's signals.csv: who could brake and who crossed at each yellow of --arc",
    )
    ap.add_argument(
        "--greens",
        metavar="SIGNALS_CSV",
        help="the truth's signals.csv: crossings per green and saturation headway at --arc",
    )
    ap.add_argument(
        "--pull-away",
        metavar="SIGNALS_CSV",
        help="the truth's signals.csv: each queue position's speeds and crossings after a green",
    )
    ap.add_argument(
        "--decel",
        action="append",
        default=[],
        metavar="VTYPE=B",
        help=f"--yellow-onsets: a vType's decel [m/s^2] (default {YELLOW_DECEL_MPS2})",
    )
    ap.add_argument("files", nargs="+", metavar="LABEL=trajectories.csv")
    o = ap.parse_args(argv)
    onsets = yellows = greens = None
    decel: dict[str, float] = {}
    for item in o.decel:
        name, sep, value = item.partition("=")
        try:
            decel[name] = float(value)
        except ValueError:
            sep = ""
        if not sep or not decel.get(name, 0.0) > 0.0:
            print(f"station_headways: --decel {item}: give VTYPE=B, B > 0", file=sys.stderr)
            return 2
    modes = [m for m in (o.start_lags, o.yellow_onsets, o.greens, o.pull_away) if m is not None]
    if len(modes) > 1:
        modes_text = "--start-lags, --yellow-onsets, --greens, --pull-away"
        print(f"station_headways: one of {modes_text}", file=sys.stderr)
        return 2
    signals_file = modes[0] if modes else None
    if signals_file is not None:
        if not Path(signals_file).is_file():
            print(f"station_headways: {signals_file}: no such signals file", file=sys.stderr)
            return 2
        signals = pd.read_csv(signals_file)
        if o.start_lags is not None or o.pull_away is not None:
            onsets = {arc: green_onsets(signals, arc) for arc in o.arc}
        elif o.greens is not None:
            got = {arc: green_windows(signals, arc) for arc in o.arc}
            greens = {a: w[w["time_s"].between(o.t0, o.t1, "left")] for a, w in got.items()}
        else:
            got = {arc: yellow_onsets(signals, arc) for arc in o.arc}  # within --from, --to
            yellows = {a: y[y["time_s"].between(o.t0, o.t1, "left")] for a, y in got.items()}
    elif len(o.arc) != 1:
        print(f"station_headways: --arc takes one point, got {len(o.arc)}", file=sys.stderr)
        return 2
    rows = {}
    for item in o.files:
        label, sep, path = item.partition("=")
        if not sep or not Path(path).is_file():
            print(
                f"station_headways: {item}: give LABEL=an existing trajectories.csv",
                file=sys.stderr,
            )
            return 2
        traj = pd.read_csv(path, usecols=COLUMNS + (["lane_index"] if greens is not None else []))
        if greens is not None:
            d = [green_discharge(traj, arc, w).assign(arc_m=arc) for arc, w in greens.items()]
            rows[label] = green_summary(pd.concat(d, ignore_index=True))
            continue
        if yellows is not None:
            cars = [at_yellow(traj, arc, y, decel).assign(arc_m=arc) for arc, y in yellows.items()]
            rows[label] = yellow_summary(pd.concat(cars, ignore_index=True))
            continue
        if onsets is not None and o.pull_away is not None:
            cars = pd.concat([pull_away(traj, arc, g) for arc, g in onsets.items()])
            table = cars.groupby("position").mean().assign(n=cars.groupby("position").size())
            print(f"{label}:\n{table.round(2).to_string()}")
            continue
        if onsets is not None:
            lags = [start_lags(traj, arc, g).assign(arc_m=arc) for arc, g in onsets.items()]
            rows[label] = lag_summary(pd.concat(lags, ignore_index=True))
            continue
        p = passages(traj, o.arc[0])
        rows[label] = summary(headways(p, o.t0, o.t1), traj["run"].nunique())
    if rows:
        print(pd.DataFrame(rows).T.round(2).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

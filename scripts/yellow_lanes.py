"""Who crosses on the yellow, per lane, against SUMO's own rule (``deploy.yellow = "sumo"``,
``sumo.stop_lines``; docs/deploy-log.md, stop 48): at each yellow onset of a stop line
(signals.csv) every vehicle moving within ``REACH_M`` upstream of it at the last sample
before the onset (the state SUMO's drivers decide from), whether it could stop by SUMO's
rule (its Euler braking distance at max(3 m/s^2, its vType's decel) within its distance to
the line; a lane without stopOffset) and what it did before the red: crossed the line, left
the trajectories before it (a turner off the section) or neither (stopped); then the queue
standing (< 0.1 m/s) within ``QUEUE_M`` of the line, per lane, at the next green.

    python scripts/yellow_lanes.py --signals GT/signals.csv --arc 279.8 --arc 566.8 \
        --decel car=4.5 --decel truck=4.0 truth=GT/trajectories.csv policy=OUT/trajectories.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REACH_M, QUEUE_M, MOVING_MPS, STANDING_MPS = 120.0, 200.0, 0.1, 0.1
FROM_S = 240.0  # past the warm-up, as station_headways
TLS_YELLOW_MIN_DECEL_MPS2 = 3.0  # SUMO's --tls.yellow.min-decel
DECEL_MPS2 = 4.5  # a vType not named with --decel


def phases(signals: pd.DataFrame, arc_m: float) -> pd.DataFrame:
    """run, yellow_s (each switch from green to yellow), red_s and green_s (the red after it
    and the green after that; inf: past the file) of the links stopping at ``arc_m``."""
    at = signals[(signals["arc_m"] - arc_m).abs() <= 0.5].sort_values(["run", "time_s"])
    at = at.drop_duplicates(["run", "time_s"])
    rows = []
    for run, g in at.groupby("run"):
        st, t = g["state"].to_numpy(), g["time_s"].to_numpy()
        green, yellow = np.isin(st, ["G", "g"]), np.isin(st, ["y", "Y"])
        for i in np.flatnonzero(yellow[1:] & green[:-1]) + 1:
            red = np.flatnonzero(~yellow[i:] & ~green[i:])
            r = i + red[0] if red.size else len(t)
            nxt = np.flatnonzero(green[r:])
            rows.append((run, t[i], t[r] if r < len(t) else np.inf,
                         t[r + nxt[0]] if nxt.size else np.inf))  # fmt: skip
    return pd.DataFrame(rows, columns=["run", "yellow_s", "red_s", "green_s"])


def euler_brake_gap(v: float, b: float, dt_s: float) -> float:
    """SUMO's brakeGap [m] in Euler steps (``sumo.stop_lines.euler_brake_gap``)."""
    steps = np.floor(v / (b * dt_s))
    return float(dt_s * (steps * v - b * dt_s * steps * (steps + 1.0) / 2.0))


def onset_cars(
    traj: pd.DataFrame, arc_m: float, ph: pd.DataFrame, decel: dict[str, float]
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per vehicle at each onset: run, arc_m, yellow_s, vehicle_id, lane_index, distance_m,
    speed_mps, can_stop (SUMO's rule), outcome (crossed / left / stopped); and per lane and
    next green: the standing vehicles within ``QUEUE_M`` and the farthest one's distance."""
    cars, queues = [], []
    for run, tr in traj.groupby("run"):
        times = np.sort(tr["time_s"].unique())
        dt = float(np.median(np.diff(times))) if len(times) > 1 else 0.5
        for y, red, green in ph.loc[ph["run"] == run, ["yellow_s", "red_s", "green_s"]].values:
            before = times[times < y]
            if y < FROM_S or not len(before) or y >= times[-1]:
                continue
            snap = tr[tr["time_s"] == before[-1]]
            near = snap[(snap["arc_m"] < arc_m) & (snap["arc_m"] > arc_m - REACH_M)]
            near = near[near["speed_mps"] > MOVING_MPS]
            win = tr[
                (tr["time_s"] >= y)
                & (tr["time_s"] < red)
                & tr["vehicle_id"].isin(near["vehicle_id"])
            ]
            crossed = set(win.loc[win["arc_m"] >= arc_m, "vehicle_id"])
            last = (
                tr[tr["vehicle_id"].isin(near["vehicle_id"])].groupby("vehicle_id")["time_s"].max()
            )
            for r in near.itertuples(index=False):
                d = arc_m - r.arc_m
                b = max(TLS_YELLOW_MIN_DECEL_MPS2, decel.get(r.vtype, DECEL_MPS2))
                out = (
                    "crossed"
                    if r.vehicle_id in crossed
                    else "left"
                    if last[r.vehicle_id] < red
                    else "stopped"
                )
                cars.append((run, arc_m, y, r.vehicle_id, r.lane_index, d, r.speed_mps,
                             euler_brake_gap(r.speed_mps, b, dt) <= d, out))  # fmt: skip
            at = times[times <= green]
            if np.isfinite(green) and len(at) and at[-1] > red:
                s = tr[tr["time_s"] == at[-1]]
                s = s[(s["arc_m"] < arc_m) & (s["arc_m"] > arc_m - QUEUE_M)]
                for lane, h in s[s["speed_mps"] < STANDING_MPS].groupby("lane_index"):
                    queues.append((run, green, lane, len(h), arc_m - h["arc_m"].min()))
    cols = ["run", "arc_m", "yellow_s", "vehicle_id", "lane_index", "distance_m", "speed_mps"]
    return (
        pd.DataFrame(cars, columns=[*cols, "can_stop", "outcome"]),
        pd.DataFrame(queues, columns=["run", "green_s", "lane_index", "standing", "back_m"]),
    )


def summary(cars: pd.DataFrame, queues: pd.DataFrame) -> pd.DataFrame:
    """Per lane: vehicles that could / could not stop, those of each that crossed, that
    left, and the queue (mean standing, back) at the next green."""
    g = cars.groupby("lane_index")
    out = pd.DataFrame({
        "could_stop": g["can_stop"].sum(),
        "could_stop_crossed": g.apply(lambda x: (x["can_stop"] & (x["outcome"] == "crossed")).sum()),
        "could_not": g["can_stop"].apply(lambda x: (~x).sum()),
        "could_not_crossed": g.apply(lambda x: (~x["can_stop"] & (x["outcome"] == "crossed")).sum()),
        "could_not_left": g.apply(lambda x: (~x["can_stop"] & (x["outcome"] == "left")).sum()),
        "could_not_stopped": g.apply(lambda x: (~x["can_stop"] & (x["outcome"] == "stopped")).sum()),
    })  # fmt: skip
    q = queues.groupby("lane_index")
    return out.join(q["standing"].mean().rename("queue")).join(
        q["back_m"].mean().rename("queue_back_m")
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--signals", type=Path, required=True, help="the ground truth's signals.csv")
    ap.add_argument("--arc", type=float, action="append", required=True, help="a stop line [m]")
    ap.add_argument("--decel", action="append", default=[], help="VTYPE=B [m/s^2]")
    ap.add_argument("runs", nargs="+", help="LABEL=trajectories.csv")
    a = ap.parse_args(argv)
    decel = {k: float(v) for k, v in (s.split("=", 1) for s in a.decel)}
    for path in (a.signals, *(Path(s.split("=", 1)[-1]) for s in a.runs)):
        if not path.is_file():
            print(f"yellow_lanes: no file {path}", file=sys.stderr)
            return 2
    signals = pd.read_csv(a.signals)
    for item in a.runs:
        label, path = item.split("=", 1)
        traj = pd.read_csv(path)
        got = [onset_cars(traj, arc, phases(signals, arc), decel) for arc in a.arc]
        cars, queues = (pd.concat(x) for x in zip(*got, strict=True))
        print(f"{label}: {cars.groupby(['run', 'arc_m', 'yellow_s']).ngroups} onsets")
        print(summary(cars, queues).round(2).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())

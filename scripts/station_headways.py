"""Headways by the follower's vType where vehicles pass a point of a one-lane stretch: from
trajectories.csv files (a ground truth's, or a deployment's with ``deploy.fcd_s`` covering
the window), each vehicle's passage of ``--arc`` (linear between its samples), the headway
to the vehicle that passed before it in the same run, kept where it passes in
[``--from``, ``--to``) s. Prints per file: passages a run, mean headway, the mean by the
follower's vType, the mean passing speed. Issue 17 (drawn 501's queue discharge at 1125 m,
docs/deploy.md):

    .venv/bin/python scripts/station_headways.py --arc 1125 --from 330 --to 600 \\
        truth=RUN/ground_truth/trajectories.csv policy=DEPLOY/policy/trajectories.csv

Only where the point has one lane: on several lanes the vehicle passing before may be on
another one.
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


def summary(h: pd.DataFrame, runs: int) -> dict[str, float]:
    """Passages a run, mean headway [s] overall and by vType, mean passing speed [m/s]."""
    out = {"passages_per_run": len(h) / max(runs, 1), "headway_s": h["headway_s"].mean()}
    out |= {f"headway_{k}_s": x for k, x in h.groupby("vtype")["headway_s"].mean().items()}
    return out | {"speed_mps": h["speed_mps"].mean()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arc", type=float, required=True, help="the point's arc [m]")
    ap.add_argument("--from", dest="t0", type=float, default=0.0, help="window start [s]")
    ap.add_argument("--to", dest="t1", type=float, default=np.inf, help="window end [s]")
    ap.add_argument("files", nargs="+", metavar="LABEL=trajectories.csv")
    o = ap.parse_args(argv)
    rows = {}
    for item in o.files:
        label, sep, path = item.partition("=")
        if not sep or not Path(path).is_file():
            print(
                f"station_headways: {item}: give LABEL=an existing trajectories.csv",
                file=sys.stderr,
            )
            return 2
        traj = pd.read_csv(path, usecols=COLUMNS)
        rows[label] = summary(headways(passages(traj, o.arc), o.t0, o.t1), traj["run"].nunique())
    print(pd.DataFrame(rows).T.round(2).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

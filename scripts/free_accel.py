"""How fast vehicles accelerate, by speed, from trajectories.csv files (a ground truth's, or a
deployment's with ``deploy.fcd_s`` covering the window): issue 17, the discharge at signals
(docs/deploy-log.md, stop 45 hY45 and stop 46 hD46). SUMO's Krauss driver dawdles: its mean
free acceleration is a (1 - sigma / 2), 1.95 m/s^2 at SUMO's defaults, and a policy's mean
action that accelerates at its vType's a (2.6) discharges a queue too fast.

Free rows (the default): a vehicle whose leader (the next vehicle ahead along the section's
arc in the same run, step and ``lane_index``, over edge ends) is more than ``--gap`` m
ahead, or none, at this sample and the next, moving (> ``MOVING_MPS``) and not braking
(its acceleration above ``NOT_BRAKING_MPS2``), from ``--from`` s on. ``--every``: every
accelerating row (above ``ACCELERATING_MPS2``) whatever its leader, e.g. in a jam's
discharge. ``--zone A0 A1``: only rows with A0 <= arc_m < A1. ``--vtype``: one vType.
The acceleration of a row is its next sample's speed less its own over the step.

Prints per file and speed bin (``--bins``, m/s) the mean acceleration, the rows, and the
share of rows above ``--cap`` (m/s^2; default SUMO's default Krauss mean, 1.95):

    .venv/bin/python scripts/free_accel.py --from 240 truth=RUN/ground_truth/trajectories.csv \\
        policy=DEPLOY/policy/trajectories.csv
    .venv/bin/python scripts/free_accel.py --every --zone 875 1500 --bins 0,10,20,30,40,50 \\
        truth=... policy=...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

COLUMNS = ["run", "time_s", "vehicle_id", "vtype", "lane_index", "arc_m", "speed_mps"]
# A row counts as moving above this speed [m/s] (a standing car's creep is not a discharge).
MOVING_MPS = 0.05
# Free rows: not braking (a car approaching a red line or a slower car far ahead decelerates).
NOT_BRAKING_MPS2 = -0.5
# ``--every``: the rows that accelerate.
ACCELERATING_MPS2 = 0.05
BINS_MPS = (0.0, 1.0, 2.6, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 20.0, 30.0, 40.0, 50.0)
# SUMO's default Krauss driver's mean free acceleration, a (1 - sigma / 2) [m/s^2].
CAP_MPS2 = 2.6 * (1.0 - 0.5 * 0.5)


def with_accel(traj: pd.DataFrame, dt_s: float | None = None) -> pd.DataFrame:
    """``traj`` with ``gap_m`` (to the next vehicle ahead along the arc on the same lane index
    at the same step, front to front; NaN: none), ``accel_next`` [m/s^2] (the next sample's speed
    less this one's, over the step) and ``gap_next_m`` (the gap at the next sample). The
    step is the file's (its smallest time difference) unless ``dt_s`` is given."""
    t = traj.sort_values(["run", "time_s", "lane_index", "arc_m"])
    lane = t.groupby(["run", "time_s", "lane_index"], sort=False)["arc_m"]
    t = t.assign(gap_m=lane.shift(-1) - t["arc_m"]).sort_values(["run", "vehicle_id", "time_s"])
    if dt_s is None:
        steps = np.diff(np.unique(t["time_s"].to_numpy()))
        dt_s = float(steps[steps > 0].min()) if len(steps) else 1.0
    own = t.groupby(["run", "vehicle_id"], sort=False)
    next_t = own["time_s"].shift(-1)
    accel = (own["speed_mps"].shift(-1) - t["speed_mps"]) / dt_s
    # a vehicle missing samples (it left the section and came back) has no next step
    accel[(next_t - t["time_s"]).sub(dt_s).abs() > 1e-6] = np.nan
    return t.assign(accel_next=accel, gap_next_m=own["gap_m"].shift(-1))


def selected(
    t: pd.DataFrame,
    gap_m: float,
    from_s: float,
    every: bool = False,
    zone: tuple[float, float] | None = None,
    vtype: str | None = None,
) -> pd.DataFrame:
    """The rows of ``with_accel``'s table the tables count (the module's doc)."""
    keep = (t["time_s"] >= from_s) & t["accel_next"].notna() & (t["speed_mps"] > MOVING_MPS)
    if every:
        keep &= t["accel_next"] > ACCELERATING_MPS2
    else:
        free_now = (t["gap_m"] > gap_m) | t["gap_m"].isna()
        free_next = (t["gap_next_m"] > gap_m) | t["gap_next_m"].isna()
        keep &= free_now & free_next & (t["accel_next"] > NOT_BRAKING_MPS2)
    if zone is not None:
        keep &= (t["arc_m"] >= zone[0]) & (t["arc_m"] < zone[1])
    if vtype is not None:
        keep &= t["vtype"] == vtype
    return t[keep]


def by_speed(rows: pd.DataFrame, bins: tuple[float, ...], cap_mps2: float) -> pd.DataFrame:
    """Per speed bin [m/s]: ``accel_mps2`` (mean), ``rows``, ``above_cap`` (share of rows
    accelerating faster than ``cap_mps2``)."""
    binned = rows.assign(bin=pd.cut(rows["speed_mps"], list(bins), right=False))
    g = binned.groupby("bin", observed=False)["accel_next"]
    return pd.DataFrame(
        {
            "accel_mps2": g.mean(),
            "rows": g.size(),
            "above_cap": g.apply(lambda a: float(np.mean(a > cap_mps2)) if len(a) else np.nan),
        }
    )


def get_options(args: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", nargs="+", metavar="LABEL=TRAJECTORIES_CSV")
    p.add_argument("--gap", type=float, default=40.0, help="free: leader beyond this [m]")
    p.add_argument("--from", dest="from_s", type=float, default=240.0, help="from [s]")
    p.add_argument("--bins", default=",".join(f"{b:g}" for b in BINS_MPS), help="m/s")
    p.add_argument("--cap", type=float, default=CAP_MPS2, help="share above it [m/s^2]")
    p.add_argument("--dt", type=float, default=None, help="step [s] (default: the file's)")
    p.add_argument("--every", action="store_true", help="every accelerating row")
    p.add_argument("--zone", nargs=2, type=float, default=None, metavar=("A0", "A1"))
    p.add_argument("--vtype", default=None, help="one vType only")
    return p.parse_args(args)


def main(args: list[str] | None = None) -> int:
    o = get_options(args)
    try:
        bins = tuple(float(b) for b in o.bins.split(","))
    except ValueError:
        print(f"--bins {o.bins!r}: accepted comma-separated speeds in m/s", file=sys.stderr)
        return 2
    if len(bins) < 2 or any(b >= c for b, c in zip(bins, bins[1:], strict=False)):
        print(f"--bins {o.bins!r}: accepted at least two increasing speeds", file=sys.stderr)
        return 2
    tables = {}
    for item in o.files:
        label, _, path = item.partition("=")
        if not path or not Path(path).is_file():
            print(f"{item}: accepted LABEL=an existing trajectories.csv", file=sys.stderr)
            return 2
        traj = pd.read_csv(path, usecols=COLUMNS)
        rows = selected(
            with_accel(traj, o.dt), o.gap, o.from_s, o.every, o.zone and tuple(o.zone), o.vtype
        )
        table = by_speed(rows, bins, o.cap)
        tables[label] = table["accel_mps2"].round(2)
        tables[f"{label}_n"] = table["rows"]
        tables[f"{label}>{o.cap:g}"] = table["above_cap"].round(2)
    print(pd.DataFrame(tables).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

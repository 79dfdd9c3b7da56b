"""Who drives into a signalised junction it cannot leave, on a one-lane arterial: from
trajectories.csv files (a ground truth's, or a deployment's with ``deploy.fcd_s`` covering
the window) and the ground truth's signals.csv, per stop line ``--arc``:

* ``in``: samples of vehicles inside the junction, from 0.5 m past the line to
  ``--junction`` m past it (netconvert's internal lanes and the first metres of the lane
  after), and how many of them are slow (below ``SLOW_MPS``) or standing (below
  ``STANDING_MPS``): SUMO's drivers keep a junction clear, a slow car in it is one that
  drove in behind a queue;
* ``wait``: samples of vehicles standing within ``NEAR_M`` before the line while it is
  green, and of those the ones whose vehicle ahead (by arc, in the same run and step) has
  less room behind it past the junction than a car's length and minGap
  (``ROOM_M``): the truth's cars wait there, at a green light.

Issue 17, arterial 1164 (docs/deploy.md, stop 47, hA47): the truth had 271 slow samples in
the first junction, the policy 1,127; the truth 351 standing at the green line, the policy
38::

    .venv/bin/python scripts/junction_entry.py --arc 266.8 --arc 540.8 \\
        --signals RUN/ground_truth/signals.csv --from 240 \\
        truth=RUN/ground_truth/trajectories.csv policy=OUT/policy/trajectories.csv

Only where the approach has one lane: on several the vehicle ahead may be on another one.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

COLUMNS = ["run", "time_s", "vehicle_id", "vtype", "arc_m", "speed_mps"]
SLOW_MPS = 3.0  # a car this slow inside a junction crept in behind a queue [m/s]
STANDING_MPS = 0.1  # SUMO's halting speed [m/s]
NEAR_M = 4.0  # standing this near before the line: first in the queue [m]
ROOM_M = 7.5  # a car's length and minGap (SUMO's passenger defaults) [m]
TRUCK_LENGTH_M, CAR_LENGTH_M = 12.0, 5.0  # the vehicle ahead's length by vType name


def load(item: str, from_s: float) -> tuple[str, pd.DataFrame]:
    """LABEL=PATH -> (label, its trajectories from ``from_s`` on, sorted by run, time, arc)."""
    label, sep, path = item.partition("=")
    if not sep or not label or not path:
        sys.exit(f"{item}: expected LABEL=TRAJECTORIES_CSV")
    if not Path(path).is_file():
        sys.exit(f"{path}: no such file")
    t = pd.read_csv(path)
    missing = [c for c in COLUMNS if c not in t.columns]
    if missing:
        sys.exit(f"{path}: missing columns {', '.join(missing)}")
    t = t.loc[t["time_s"] >= from_s, COLUMNS]
    return label, t.sort_values(["run", "time_s", "arc_m"], kind="stable").reset_index(drop=True)


def with_ahead(t: pd.DataFrame) -> pd.DataFrame:
    """``t`` (sorted by run, time, arc) with the arc, speed and length of the vehicle ahead
    at the same step (NaN: none)."""
    nxt = t.groupby(["run", "time_s"], sort=False)[["arc_m", "speed_mps", "vtype"]].shift(-1)
    length = np.where(nxt["vtype"].astype(str).str.contains("truck"), TRUCK_LENGTH_M, CAR_LENGTH_M)
    return t.assign(
        ahead_arc=nxt["arc_m"], ahead_mps=nxt["speed_mps"], ahead_len=np.where(
            nxt["arc_m"].notna(), length, np.nan)
    )  # fmt: skip


def green_at(signals: pd.DataFrame, arc_m: float) -> pd.DataFrame:
    """run, time_s where the line at ``arc_m`` (nearest in signals.csv, within 1 m) is
    green (G or g on any of its links)."""
    at = signals[(signals["arc_m"] - arc_m).abs() < 1.0]
    if at.empty:
        sys.exit(f"signals.csv: no signal at arc {arc_m} m (within 1 m)")
    g = at[at["state"].isin(["G", "g"])][["run", "time_s"]].drop_duplicates()
    return g


def line_counts(t: pd.DataFrame, arc_m: float, junction_m: float, green: pd.DataFrame) -> dict:
    """The module docstring's counts at the line ``arc_m``."""
    inside = t[(t["arc_m"] > arc_m + 0.5) & (t["arc_m"] < arc_m + junction_m)]
    near = t[(t["arc_m"] > arc_m - NEAR_M) & (t["arc_m"] <= arc_m)]
    near = near.merge(green, on=["run", "time_s"])
    wait = near[near["speed_mps"] < STANDING_MPS]
    room = wait["ahead_arc"] - wait["ahead_len"] - (arc_m + junction_m)
    return {
        "in": len(inside),
        "slow": int((inside["speed_mps"] < SLOW_MPS).sum()),
        "standing": int((inside["speed_mps"] < STANDING_MPS).sum()),
        "wait": len(wait),
        "wait_no_room": int((room < ROOM_M).sum()),
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", metavar="LABEL=TRAJECTORIES_CSV")
    p.add_argument("--arc", type=float, action="append", required=True, help="stop line [m]")
    p.add_argument("--signals", type=Path, required=True, help="ground truth's signals.csv")
    p.add_argument("--junction", type=float, default=19.0, help="past the line [m]")
    p.add_argument("--from", dest="from_s", type=float, default=240.0, help="from [s]")
    a = p.parse_args(argv)
    if not a.signals.is_file():
        sys.exit(f"{a.signals}: no such file")
    if not 0.5 < a.junction <= 100.0:
        sys.exit(f"--junction: {a.junction} m, accepted (0.5, 100]")
    signals = pd.read_csv(a.signals)
    greens = {arc: green_at(signals, arc) for arc in a.arc}
    rows = {}
    for item in a.files:
        label, t = load(item, a.from_s)
        t = with_ahead(t)
        for arc in a.arc:
            rows[(label, arc)] = line_counts(t, arc, a.junction, greens[arc])
    out = pd.DataFrame(rows).T
    out.index.names = ["file", "line_m"]
    print(out.to_string())


if __name__ == "__main__":
    main()

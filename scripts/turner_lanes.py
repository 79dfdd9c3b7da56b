"""Turners in the wrong lane at a signal, and the greens they stall: from trajectories.csv
files (a ground truth's, or a deployment's with ``deploy.fcd_s`` covering the window) and
the ground truth's signals.csv. Issue 17, drawn arterial 565 (docs/deploy.md, stop 44,
hD44): turners still outside their turn lane at the stop line stand there through the
green and hold up the lane behind them.

Per file:

* the turners (vehicles whose id starts with ``--route``, SUMO's ``flow.n``) on the
  approach: the share not on ``--turn-lane`` where each first shows in a band of distance
  before the line (``BANDS_M``), and those standing (< ``STANDING_MPS``) within
  ``AT_LINE_M`` of the line on another lane, with their vehicle-seconds;
* per lane of the line: crossings per green (a vehicle passing ``--line`` between two
  samples, from a green onset to the next red), and the stalled greens: no crossing in the
  first ``STALL_S`` s, or a gap between crossings longer than ``STALL_S`` s.

    .venv/bin/python scripts/turner_lanes.py --line 775.8 --signal-id j3 --route off3 \\
        --signals RUN/ground_truth/signals.csv --from 240 --to 900 \\
        truth=RUN/ground_truth/trajectories.csv policy=DEPLOY/policy/trajectories.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

BANDS_M = ((200.0, 150.0), (100.0, 60.0), (30.0, 0.0))  # (far, near) before the line [m]
STANDING_MPS = 0.5
AT_LINE_M = 10.0
STALL_S = 10.0
GREEN = ("G", "g")


def read(path: Path, what: str, columns: tuple[str, ...]) -> pd.DataFrame:
    """A CSV with ``columns``, else a one-line error naming the file."""
    if not path.is_file():
        raise SystemExit(f"turner_lanes.py: {path} not found ({what})")
    d = pd.read_csv(path)
    missing = [c for c in columns if c not in d.columns]
    if missing:
        raise SystemExit(f"turner_lanes.py: {path}: no column(s) {missing} ({what})")
    return d


def greens(signals: pd.DataFrame, signal_id: str, t0: float, t1: float) -> pd.DataFrame:
    """Per run and lane of ``signal_id``: each green onset in [t0, t1) and the next red onset
    after it (inf where none is recorded): columns run, lane, g0, r0."""
    s = signals[signals["signal_id"] == signal_id].sort_values(["run", "lane_index", "time_s"])
    rows = []
    for (run, lane), g in s.groupby(["run", "lane_index"]):
        t, green = g["time_s"].to_numpy(), g["state"].isin(GREEN).to_numpy()
        red = g["state"].isin(("r",)).to_numpy()
        onsets = np.flatnonzero(green & ~np.r_[False, green[:-1]])
        for k in onsets:
            if not t0 <= t[k] < t1:
                continue
            later = np.flatnonzero(red[k:])
            r0 = t[k + later[0]] if later.size else np.inf
            rows.append({"run": run, "lane": int(lane), "g0": t[k], "r0": r0})
    return pd.DataFrame(rows, columns=["run", "lane", "g0", "r0"])


def crossings(traj: pd.DataFrame, line_m: float) -> pd.DataFrame:
    """Each vehicle's passage of ``line_m``: run, time_s (its first sample past the line),
    lane (its lane at the sample before)."""
    d = traj.sort_values(["run", "vehicle_id", "time_s"])
    prev = d.groupby(["run", "vehicle_id"])[["arc_m", "lane_index"]].shift()
    past = (prev["arc_m"] < line_m) & (d["arc_m"] >= line_m)
    return pd.DataFrame(
        {
            "run": d.loc[past, "run"],
            "time_s": d.loc[past, "time_s"],
            "lane": prev.loc[past, "lane_index"].astype(int),
        }
    )


def per_green(cross: pd.DataFrame, green: pd.DataFrame) -> pd.DataFrame:
    """Per green: its crossings, the first one's time after the onset and the longest gap
    (onset to first crossing counted) [s]; stalled where either exceeds ``STALL_S``."""
    rows = []
    for g in green.itertuples():
        c = cross[(cross["run"] == g.run) & (cross["lane"] == g.lane)]
        t = np.sort(c["time_s"][(c["time_s"] >= g.g0) & (c["time_s"] < g.r0)].to_numpy())
        gaps = np.diff(np.r_[g.g0, t])
        first = float(gaps[0]) if t.size else np.inf
        longest = float(gaps.max()) if t.size else np.inf
        rows.append({"lane": g.lane, "n": t.size, "first_s": first, "longest_gap_s": longest})
    r = pd.DataFrame(rows, columns=["lane", "n", "first_s", "longest_gap_s"])
    return r.assign(stalled=(r["first_s"] > STALL_S) | (r["longest_gap_s"] > STALL_S))


def turners(traj: pd.DataFrame, route: str, line_m: float, turn_lane: int) -> dict[str, float]:
    """The turners of ``route`` before ``line_m``: how many, the share off ``turn_lane`` in
    each band (the lane where each first shows there), and those standing near the line on
    another lane (vehicles, vehicle-seconds)."""
    d = traj[traj["vehicle_id"].astype(str).str.startswith(f"{route}.")]
    d = d[(d["arc_m"] < line_m) & (d["arc_m"] >= line_m - BANDS_M[0][0])]
    dt = float(np.median(np.diff(np.unique(traj["time_s"])))) if len(traj) > 1 else 0.0
    out: dict[str, float] = {"turners": float(d.groupby("run")["vehicle_id"].nunique().sum())}
    for far, near in BANDS_M:
        w = d[(d["arc_m"] >= line_m - far) & (d["arc_m"] < line_m - near)]
        first = w.sort_values("time_s").groupby(["run", "vehicle_id"])["lane_index"].first()
        out[f"off lane {far:.0f}-{near:.0f} m %"] = (
            float(100.0 * (first != turn_lane).mean()) if len(first) else np.nan
        )
    s = d[
        (d["arc_m"] >= line_m - AT_LINE_M)
        & (d["lane_index"] != turn_lane)
        & (d["speed_mps"] < STANDING_MPS)
    ]
    out["standing off lane: vehicles"] = float(s.groupby("run")["vehicle_id"].nunique().sum())
    out["standing off lane: veh-s"] = len(s) * dt
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", nargs="+", help="LABEL=trajectories.csv")
    p.add_argument("--signals", type=Path, required=True, help="the ground truth's signals.csv")
    p.add_argument("--signal-id", required=True, help="the signal of the line (signals.csv)")
    p.add_argument("--line", type=float, required=True, help="the stop line's arc [m]")
    p.add_argument("--route", required=True, help="the turners' route (vehicle id prefix)")
    p.add_argument("--turn-lane", type=int, default=0, help="the lane they turn from")
    p.add_argument("--from", dest="t0", type=float, default=0.0, help="window start [s]")
    p.add_argument("--to", dest="t1", type=float, default=np.inf, help="window end [s]")
    p.add_argument("--runs", type=int, nargs="+", help="only these runs (default: every one)")
    args = p.parse_args(argv)
    if not args.t0 < args.t1:
        print("turner_lanes.py: --from must be below --to", file=sys.stderr)
        return 2
    cols = ("run", "time_s", "signal_id", "lane_index", "state")
    green = greens(read(args.signals, "signals.csv", cols), args.signal_id, args.t0, args.t1)
    if green.empty:
        print(f"turner_lanes.py: {args.signals}: no green of {args.signal_id!r} in the window",
              file=sys.stderr)  # fmt: skip
        return 2
    turn_rows, lane_rows = {}, {}
    for item in args.files:
        label, _, path = item.partition("=")
        if not path:
            raise SystemExit(f"turner_lanes.py: {item!r}: expected LABEL=trajectories.csv")
        cols = ("run", "time_s", "vehicle_id", "lane_index", "arc_m", "speed_mps")
        traj = read(Path(path), "trajectories.csv", cols)
        traj = traj[(traj["time_s"] >= args.t0) & (traj["time_s"] < args.t1)]
        if args.runs is not None:
            traj = traj[traj["run"].isin(args.runs)]
        g = green[green["run"].isin(traj["run"].unique())]
        turn_rows[label] = turners(traj, args.route, args.line, args.turn_lane)
        pg = per_green(crossings(traj, args.line), g)
        lane_rows[label] = pg.groupby("lane").agg(
            greens=("n", "size"), crossings_per_green=("n", "mean"), stalled=("stalled", "sum")
        )
    pd.set_option("display.width", 200)
    print(f"turners {args.route!r} before {args.line} m (turn lane {args.turn_lane}):")
    print(pd.DataFrame(turn_rows).round(1).to_string(), "\n")
    print(f"per lane at {args.signal_id} ({args.line} m): crossings per green, stalled greens")
    print(pd.concat(lane_rows, axis=1).round(2).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Where a deployment's speed error lies on a signalised section: ``scripts/deploy_runs.py``
outputs (their ``deploy_comparison.csv``) split by station zone around the stop lines
(``--lines``, arc positions [m] of the lines) and by lane, against the ground truth, per
folder and method. Zones: ``entry`` (before ``--entry`` m), ``exit`` (past ``--exit`` m),
else by the signed distance d to the nearest line: ``far before`` (d < -20), ``before``
(-20 <= d < -1), ``at line`` (-1 <= d < 0), ``past`` (0 <= d < 40), ``far past`` (d >= 40).
Per lane: speed bias / RMSE of the lane rows and the lane's share of the station's flow
(method against truth). Issue 17, drawn arterial 565 (docs/deploy.md, stop 44, hD44):

    .venv/bin/python scripts/deploy_zones.py policy=OUT/deploy_comparison.csv:policy \\
        sumo_default=BASE/deploy_comparison.csv:sumo_default --lines 253.8 514.8 775.8

Each argument is LABEL=PATH[:METHOD] (METHOD defaults to the label), before ``--lines``
(which takes every number after it).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ZONES = ("entry", "far before", "before", "at line", "past", "far past", "exit")


def zone_of(arc_m: float, lines: np.ndarray, entry_m: float, exit_m: float) -> str:
    """The zone of a station at ``arc_m`` (module docstring)."""
    if arc_m < entry_m:
        return "entry"
    if arc_m > exit_m:
        return "exit"
    d = arc_m - lines[np.argmin(np.abs(arc_m - lines))]
    if d < -20.0:
        return "far before"
    if d < -1.0:
        return "before"
    if d < 0.0:
        return "at line"
    return "past" if d < 40.0 else "far past"


def load(arg: str) -> tuple[str, pd.DataFrame]:
    """LABEL=PATH[:METHOD] -> (label, the method's rows with both speeds measured)."""
    if "=" not in arg:
        raise SystemExit(f"deploy_zones.py: {arg!r}: expected LABEL=PATH[:METHOD]")
    label, rest = arg.split("=", 1)
    path, _, method = rest.partition(":")
    method = method or label
    if not Path(path).is_file():
        raise SystemExit(f"deploy_zones.py: {path} not found (a scripts/deploy_runs.py --out)")
    c = pd.read_csv(path)
    c = c[c["method"] == method]
    if c.empty:
        raise SystemExit(f"deploy_zones.py: {path}: no rows of method {method!r}")
    return label, c


def scores(rows: pd.DataFrame) -> pd.Series:
    """n, speed bias and RMSE [m/s] of rows with both speeds."""
    r = rows[rows["speed_truth_mps"].notna() & rows["speed_method_mps"].notna()]
    e = r["speed_method_mps"] - r["speed_truth_mps"]
    return pd.Series({"n": len(r), "bias": float(e.mean()), "rmse": float(np.sqrt((e**2).mean()))})


def lane_shares(rows: pd.DataFrame) -> pd.DataFrame:
    """Per lane: the lane's share of its station's flow summed over runs and intervals,
    truth and method (in %)."""
    lanes = rows[rows["lane"] >= 0]
    f = lanes.groupby(["station", "lane"])[["flow_truth_vph", "flow_method_vph"]].sum()
    tot = f.groupby(level="station").transform("sum")
    share = (100.0 * f / tot).groupby(level="lane").mean()
    return share.rename(columns={"flow_truth_vph": "truth %", "flow_method_vph": "method %"})


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("items", nargs="+", help="LABEL=deploy_comparison.csv[:METHOD]")
    p.add_argument("--lines", type=float, nargs="+", required=True, help="stop lines' arc [m]")
    p.add_argument("--entry", type=float, default=60.0, help="entry zone before this arc [m]")
    p.add_argument("--exit", type=float, default=900.0, help="exit zone past this arc [m]")
    args = p.parse_args(argv)
    if args.entry >= args.exit:
        print("deploy_zones.py: --entry must be below --exit", file=sys.stderr)
        return 2
    lines = np.asarray(sorted(args.lines), dtype=float)
    by_zone, by_lane, shares = {}, {}, {}
    for item in args.items:
        label, c = load(item)
        c = c.assign(zone=[zone_of(a, lines, args.entry, args.exit) for a in c["arc_m"]])
        st = c[c["lane"] == -1]
        z = st.groupby("zone").apply(scores, include_groups=False)
        by_zone[label] = z.reindex([q for q in ZONES if q in z.index])
        by_lane[label] = (
            c[c["lane"] >= 0].groupby(["zone", "lane"]).apply(scores, include_groups=False)
        )
        shares[label] = lane_shares(c)
    pd.set_option("display.width", 200)
    print("stations (lane -1), bias / RMSE [m/s] by zone:")
    print(pd.concat(by_zone, axis=1).round(2).to_string(), "\n")
    print("lane rows, bias / RMSE [m/s] by zone and lane:")
    print(pd.concat(by_lane, axis=1).round(2).to_string(), "\n")
    print("lane share of the station's flow (mean over stations) [%]:")
    print(pd.concat(shares, axis=1).round(1).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

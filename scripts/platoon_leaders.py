"""Who sets the speed of a stream: per detector passages (``detector_passages.csv``, written by
the ground truth and by each method of ``scripts/deploy_runs.py``) on the chosen detectors,
split into platoon leaders (the time headway to the previous passage at the same detector
above ``--free-headway`` s) and followers: count, mean speed, median headway, per source and
per time bin. Where a deployment is as dense as another (the same headways) but slower, its
leaders are slower: their desired speeds, not the following.

Issue 17, drawn motorway 522 (docs/deploy.md, stop 47, hM47): on its one-lane edge m1 the
policy's stream (``policy.driver_entry = "auto"``) runs at the headway of ``sumo_default``'s
(1.5 s; the truth's 1.8 s) but 1.1 m/s slower, its leaders 0.8 m/s slower:

    .venv/bin/python scripts/platoon_leaders.py \\
        truth=RUN/ground_truth/detector_passages.csv \\
        policy=OUT/policy/detector_passages.csv sumo=OUT/sumo_default/detector_passages.csv \\
        --detectors _m1_ --runs 1 [--bins 0 150 300 450 600 750]

Each source is LABEL=PATH; ``--detectors``: a substring (regular expression) of the detector
ids kept; ``--runs``: the runs kept (default: every run of each file).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

# A passage more than this after the previous one at its detector leads its platoon: beyond
# ``env.observed_drivers``' free headway (2 s) with a margin, so a follower at pace is not one.
FREE_HEADWAY_S = 4.0
COLUMNS = ("run", "detector_id", "time_s", "vehicle_id", "speed_mps")


def passages(path: Path, detectors: str, runs: list[int] | None) -> pd.DataFrame:
    """The passages of ``path`` at the detectors matching ``detectors`` (of ``runs``; None:
    all), each with its headway [s] to the previous passage at its detector (NaN: the first)."""
    if not path.is_file():
        raise SystemExit(f"platoon_leaders.py: {path} not found (detector_passages.csv)")
    d = pd.read_csv(path)
    missing = [c for c in COLUMNS if c not in d.columns]
    if missing:
        raise SystemExit(f"platoon_leaders.py: {path}: no column {', '.join(missing)}")
    d = d[d["detector_id"].astype(str).str.contains(detectors)]
    if runs is not None:
        d = d[d["run"].isin(runs)]
    if d.empty:
        raise SystemExit(f"platoon_leaders.py: {path}: no passage at detectors {detectors!r}")
    d = d.sort_values(["run", "detector_id", "time_s"])
    return d.assign(headway_s=d.groupby(["run", "detector_id"])["time_s"].diff())


def leaders(d: pd.DataFrame, free_headway_s: float, bins_s: list[float] | None) -> pd.DataFrame:
    """Per (time bin, or "all"; leader or follower): passages, mean speed [m/s] and median
    headway [s]. A first passage at its detector (no headway) counts as neither."""
    d = d[d["headway_s"].notna()]
    d = d.assign(role=np.where(d["headway_s"] > free_headway_s, "leader", "follower"))
    when = pd.cut(d["time_s"], bins_s, right=False).astype(str) if bins_s else "all"
    d = d.assign(when=when)
    every = d.assign(role="all")
    g = pd.concat([d, every]).groupby(["when", "role"])
    return g.agg(
        n=("speed_mps", "size"),
        speed_mps=("speed_mps", "mean"),
        headway_s=("headway_s", "median"),
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sources", nargs="+", help="LABEL=PATH of a detector_passages.csv")
    p.add_argument("--detectors", required=True, help="substring (regex) of detector ids")
    p.add_argument("--runs", type=int, nargs="+", default=None)
    p.add_argument("--free-headway", type=float, default=FREE_HEADWAY_S)
    p.add_argument("--bins", type=float, nargs="+", default=None, help="time bin edges [s]")
    args = p.parse_args(argv)
    if args.bins is not None and (len(args.bins) < 2 or any(np.diff(args.bins) <= 0)):
        print("platoon_leaders.py: --bins: at least 2 increasing edges [s]", file=sys.stderr)
        return 2
    if args.free_headway <= 0:
        print("platoon_leaders.py: --free-headway: a positive number of seconds", file=sys.stderr)
        return 2
    tables = {}
    for source in args.sources:
        label, sep, path = source.partition("=")
        if not sep or not label or not path:
            print(f"platoon_leaders.py: {source!r}: give LABEL=PATH", file=sys.stderr)
            return 2
        d = passages(Path(path), args.detectors, args.runs)
        tables[label] = leaders(d, args.free_headway, args.bins)
    t = pd.concat(tables, names=["source"]).reset_index()
    wide = t.pivot_table(
        index=["when", "role"], columns="source", values=["n", "speed_mps", "headway_s"]
    )
    with pd.option_context("display.width", 200):
        print(wide.round(2).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""How much of a deployment's figure belongs to the policy: the spread of several PPO seeds'
deployments (``scripts/deploy_runs.py`` outputs, one folder per seed) run by run.

Prints each folder's speed RMSE per run and over all runs, the seeds' standard deviation of
each, how the seeds rank from one run to another (Spearman across seeds for every pair of
runs), and the split-half test: for every split of the runs into two halves, how well the
seeds' mean RMSE on one half ranks them on the other (Spearman) and what keeping the best
seed on the first half gains on the second against the seeds' mean there (m/s; negative: it
loses). Where the halves do not rank the seeds alike, a seed's figure is mostly the runs'
noise, not the policy's: choosing a seed by its deployment on training runs cannot help,
and a before -> after of one seed is within that noise (drawn 522, stop 49: docs/deploy-log.md).

    .venv/bin/python scripts/seed_spread.py DIR [DIR ...] [--method policy] [--csv OUT]
"""

from __future__ import annotations

import argparse
import sys
from itertools import combinations
from pathlib import Path

import pandas as pd
from scipy.stats import spearmanr


def per_run(folder: Path, method: str) -> pd.Series:
    """``method``'s speed RMSE [m/s] per run in ``folder``'s deploy_runs.csv, and "all" (the
    deploy_summary.csv figure over every run)."""
    runs, summary = folder / "deploy_runs.csv", folder / "deploy_summary.csv"
    for path in (runs, summary):
        if not path.is_file():
            raise SystemExit(f"seed_spread.py: {path} not found (a scripts/deploy_runs.py --out)")
    r = pd.read_csv(runs)
    r = r[r["method"] == method]
    s = pd.read_csv(summary)
    s = s[s["method"] == method]
    if r.empty or s.empty:
        raise SystemExit(f"seed_spread.py: {runs}: no method {method!r}")
    out = r.set_index("run")["speed_rmse_mps"].sort_index()
    out.index = [str(i) for i in out.index]
    out["all"] = float(s["speed_rmse_mps"].iloc[0])
    return out


def split_half(table: pd.DataFrame) -> pd.DataFrame:
    """For every split of the runs (columns other than "all") into a first half (half of
    them, rounded down) and a second (the rest), each way round: the Spearman rank
    correlation across seeds of the mean RMSE on the first half with that on the second, and
    the gain [m/s] of the seed best on the first half, on the second, over the seeds' mean."""
    runs = [c for c in table.columns if c != "all"]
    rows = []
    for first in combinations(runs, len(runs) // 2):
        second = [r for r in runs if r not in first]
        a, b = table[list(first)].mean(axis=1), table[second].mean(axis=1)
        rows.append(
            {
                "first": " ".join(first),
                "second": " ".join(second),
                "spearman": float(spearmanr(a, b).statistic),
                "gain_mps": float(b.mean() - b[a.idxmin()]),
            }
        )
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path, help="deploy_runs.py outputs, one per seed")
    ap.add_argument("--method", default="policy")
    ap.add_argument("--csv", type=Path, help="write the per-run table here")
    args = ap.parse_args(argv)
    if len(args.folders) < 3:
        raise SystemExit("seed_spread.py: at least 3 folders (seeds) to rank")
    table = pd.DataFrame({f.name: per_run(f, args.method) for f in args.folders}).T
    if table.isna().any().any():
        raise SystemExit("seed_spread.py: the folders do not hold the same runs")
    pd.set_option("display.width", 200)
    print(f"speed RMSE [m/s] per run ({args.method}):")
    print(table.round(3).to_string())
    print("seeds' sd: " + ", ".join(f"{c} {table[c].std(ddof=1):.3f}" for c in table.columns))
    runs = [c for c in table.columns if c != "all"]
    pairs = [(a, b, spearmanr(table[a], table[b]).statistic) for a, b in combinations(runs, 2)]
    print(
        "run against run, Spearman across seeds: "
        + ", ".join(f"{a}-{b} {r:+.2f}" for a, b, r in pairs)
    )
    halves = split_half(table)
    print("split-half (the first half's mean ranks the seeds on the second):")
    print(halves.round(3).to_string(index=False))
    print(
        f"mean Spearman {halves['spearman'].mean():+.2f}, mean gain of the best on the first "
        f"half {halves['gain_mps'].mean():+.3f} m/s"
    )
    if args.csv:
        table.to_csv(args.csv)
    return 0


if __name__ == "__main__":
    sys.exit(main())

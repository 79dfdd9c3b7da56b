"""Where two deployments differ: ``scripts/deploy_runs.py`` outputs (their
``deploy_comparison.csv``, the station rows) split by the stations' arc position (before /
after ``--cut`` metres) and by interval (``--bins`` edges, s), speed RMSE, speed bias and
flow bias against the ground truth per folder; then per run (the split by position).
How drawn 522's loss with ``deploy.merge_reach = "occupation"`` was found to lie
downstream of its lane drop (docs/deploy-log.md, stop 43, hO43).

    .venv/bin/python scripts/deploy_split.py DIR_A DIR_B [...] --cut 700 \\
        [--bins 0 120 300 600 720] [--method policy]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd


def station_rows(folder: Path, method: str) -> pd.DataFrame:
    """The station rows (lane -1) of ``method`` in ``folder``'s deploy_comparison.csv where
    both the truth and the method measured a speed."""
    path = folder / "deploy_comparison.csv"
    if not path.is_file():
        raise SystemExit(f"deploy_split.py: {path} not found (a scripts/deploy_runs.py --out)")
    c = pd.read_csv(path)
    c = c[(c["lane"] == -1) & (c["method"] == method)]
    if c.empty:
        raise SystemExit(f"deploy_split.py: {path}: no station rows of method {method!r}")
    return c[c["speed_truth_mps"].notna() & c["speed_method_mps"].notna()]


def split(rows: pd.DataFrame, cut_m: float, bins_s: list[float]) -> pd.DataFrame:
    """Per (where: "up" at or before ``cut_m``, else "down"; interval bin; run "all"), and
    per (where, run, bin "all"): n, speed RMSE, speed bias [m/s] and flow bias [veh/h]."""
    c = rows.assign(
        err=rows["speed_method_mps"] - rows["speed_truth_mps"],
        flow_err=rows["flow_method_vph"] - rows["flow_truth_vph"],
        where=np.where(rows["arc_m"] > cut_m, "down", "up"),
        when=pd.cut(rows["begin_s"], bins_s, right=False).astype(str),
    )

    def scores(g: pd.DataFrame) -> pd.Series:
        return pd.Series(
            {
                "n": len(g),
                "speed_rmse_mps": float(np.sqrt((g["err"] ** 2).mean())),
                "speed_bias_mps": float(g["err"].mean()),
                "flow_bias_vph": float(g["flow_err"].mean()),
            }
        )

    by_when = c.groupby(["where", "when"]).apply(scores, include_groups=False).reset_index()
    by_run = c.groupby(["where", "run"]).apply(scores, include_groups=False).reset_index()
    return pd.concat([by_when.assign(run="all"), by_run.assign(when="all")], ignore_index=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", type=Path, nargs="+", help="scripts/deploy_runs.py --out folders")
    p.add_argument("--cut", type=float, required=True, help="arc position [m] up / down")
    p.add_argument("--bins", type=float, nargs="+", default=[0.0, 120.0, 300.0, 600.0, 1e9])
    p.add_argument("--method", default="policy")
    args = p.parse_args(argv)
    if len(args.bins) < 2 or any(np.diff(args.bins) <= 0):
        print("deploy_split.py: --bins: at least 2 increasing edges [s]", file=sys.stderr)
        return 2
    tables = [
        split(station_rows(f, args.method), args.cut, args.bins).assign(folder=f.name)
        for f in args.folders
    ]
    t = pd.concat(tables, ignore_index=True)
    for value in ("speed_rmse_mps", "speed_bias_mps", "flow_bias_vph"):
        wide = t.pivot_table(index=["where", "run", "when"], columns="folder", values=value)
        print(f"{value}:\n{wide[[f.name for f in args.folders]].round(2).to_string()}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

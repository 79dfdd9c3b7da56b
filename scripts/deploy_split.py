"""Where two deployments differ: ``scripts/deploy_runs.py`` outputs (their
``deploy_comparison.csv``, the station rows) split by the stations' arc position (before /
after ``--cut`` metres) and by interval (``--bins`` edges, s), speed RMSE, speed bias and
flow bias against the ground truth per folder; then per run (the split by position).
How drawn 522's loss with ``deploy.merge_reach = "occupation"`` was found to lie
downstream of its lane drop (docs/deploy-log.md, stop 43, hO43). Then per zone the mean
squared speed error taken apart (``decompose``): the level (bias squared), the size of the
swings (the method's speed sd against the truth's, over the zone's station-intervals) and
their timing (what is left: 2 sd sd (1 - correlation)), which tells a level that a rule could
mend from waves and platoons that come at other times (drawn 522, stop 51, hM51).

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


def decompose(rows: pd.DataFrame, cut_m: float) -> pd.DataFrame:
    """Per zone ("up" at or before ``cut_m``, "down" after, "all"): n, speed RMSE and its
    square taken apart over the zone's station-intervals (every run): ``level`` the bias
    squared, ``swing`` (sd_method - sd_truth)^2, ``timing`` 2 sd_method sd_truth (1 - corr),
    summing to the MSE (population sds); sd_truth, sd_method, corr."""

    def parts(g: pd.DataFrame) -> pd.Series:
        t, m = g["speed_truth_mps"].to_numpy(), g["speed_method_mps"].to_numpy()
        sd_t, sd_m = float(t.std()), float(m.std())
        cov = float(((t - t.mean()) * (m - m.mean())).mean())
        corr = cov / (sd_t * sd_m) if sd_t > 0 and sd_m > 0 else float("nan")
        return pd.Series(
            {
                "n": len(g),
                "speed_rmse_mps": float(np.sqrt(((m - t) ** 2).mean())),
                "level": float((m - t).mean() ** 2),
                "swing": (sd_m - sd_t) ** 2,
                "timing": 2.0 * (sd_t * sd_m - cov),
                "sd_truth": sd_t,
                "sd_method": sd_m,
                "corr": corr,
            }
        )

    where = np.where(rows["arc_m"] > cut_m, "down", "up")
    zones = [parts(rows[where == z]).rename(z) for z in ("up", "down") if (where == z).any()]
    return pd.DataFrame([*zones, parts(rows).rename("all")])


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
    print("MSE = level (bias^2) + swing ((sd_method - sd_truth)^2) + timing (2 sd sd (1 - corr)):")
    for f in args.folders:
        print(
            f"{f.name}:\n{decompose(station_rows(f, args.method), args.cut).round(3).to_string()}\n"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

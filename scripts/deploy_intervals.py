"""A deployment's summary shares when its detector intervals are pooled into longer ones.

GEH < 5 in 85% of the counts is a calibration criterion for hourly flows (TAG M3.1); a
deployment compares the scenario's detector intervals (Bremen: 30 s, where one vehicle is
120 veh/h), so its shares measure when each car passes as much as the flow. This script
reads ``deploy_comparison.csv`` of one or more deploy folders and prints, per method, the
summary's shares and speed RMSE (``deploy.compare.detector_scores``) with every station's
intervals pooled in blocks of k (whole blocks only): flows averaged, speeds the
flow-weighted harmonic mean (the space-mean speed of the vehicles that passed), densities
averaged. k = 1 reproduces ``deploy_summary.csv``.

    python scripts/deploy_intervals.py DEPLOY_DIR [DEPLOY_DIR ...] [--blocks 1 2 4 10]
        [--runs 1]

Measured 2026-11-26 on highway_bremen (docs/deploy.md, "Measured").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.deploy.compare import (
    ALL_LANES,
    COMPARISON_COLUMNS,
    detector_scores,
    geh,
    relative_error,
)

GROUP = ["method", "run", "station", "lane", "block"]


def pooled(comparison: pd.DataFrame, k: int) -> pd.DataFrame:
    """``comparison``'s station rows pooled in blocks of k intervals, in its schema."""
    c = comparison[comparison["lane"] == ALL_LANES].copy()
    length = float((c["end_s"] - c["begin_s"]).median())
    c["block"] = np.floor(c["begin_s"] / (k * length) + 1e-9).astype(int)
    size = c.groupby(GROUP)["begin_s"].transform("size")
    c = c[size == k]
    for side in ("truth", "method"):
        q, v = c[f"flow_{side}_vph"], c[f"speed_{side}_mps"]
        passed = np.isfinite(v) & (v > 0) & (q > 0)
        c[f"w_{side}"] = np.where(passed, q, 0.0)
        c[f"inv_{side}"] = np.where(passed, q / np.where(passed, v, 1.0), 0.0)
    agg = (
        c.groupby(GROUP)
        .agg(
            arc_m=("arc_m", "first"),
            begin_s=("begin_s", "min"),
            end_s=("end_s", "max"),
            flow_truth_vph=("flow_truth_vph", "mean"),
            flow_method_vph=("flow_method_vph", "mean"),
            density_truth_vpkm=("density_truth_vpkm", "mean"),
            density_method_vpkm=("density_method_vpkm", "mean"),
            w_truth=("w_truth", "sum"),
            inv_truth=("inv_truth", "sum"),
            w_method=("w_method", "sum"),
            inv_method=("inv_method", "sum"),
        )
        .reset_index()
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        for side in ("truth", "method"):
            w, inv = agg[f"w_{side}"], agg[f"inv_{side}"]
            agg[f"speed_{side}_mps"] = np.where(inv > 0, w / inv, np.nan)
    agg["geh"] = geh(agg["flow_method_vph"], agg["flow_truth_vph"])
    agg["speed_rel_error"] = relative_error(agg["speed_method_mps"], agg["speed_truth_mps"])
    return agg.reindex(columns=COMPARISON_COLUMNS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", type=Path, nargs="+")
    ap.add_argument("--blocks", type=int, nargs="+", default=[1, 2, 4, 10])
    ap.add_argument("--runs", type=int, nargs="*", default=None, help="only these runs")
    args = ap.parse_args()
    rows = []
    for folder in args.folders:
        comp = pd.read_csv(folder / "deploy_comparison.csv")
        if args.runs:
            comp = comp[comp["run"].isin(args.runs)]
        for k in args.blocks:
            table = pooled(comp, k)
            length = float((table["end_s"] - table["begin_s"]).median())
            for method, part in table.groupby("method", sort=False):
                s = detector_scores(part)
                rows.append(
                    {
                        "folder": folder.name,
                        "method": method,
                        "interval_s": length,
                        "station_intervals": s["station_intervals"],
                        "geh_below_5": s["share_geh_below_5"],
                        "speed_within_5pct": s["share_speed_within_5pct"],
                        "speed_rmse_mps": s["speed_rmse_mps"],
                    }
                )
    print(pd.DataFrame(rows).round(3).to_string(index=False))


if __name__ == "__main__":
    main()

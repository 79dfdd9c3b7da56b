"""A deployment's shares at several comparison intervals, recomputed from its folders.

``deploy.compare_interval_s`` sets the one interval ``macromicro deploy`` writes; this
reads deploy folders (``deploy_manifest.json`` names the ground truth, the method folders
sit beside it), pools the detectors' intervals as the deployment would
(``deploy.intervals``) and prints, per folder, method and interval, the summary's station
figures (``deploy.compare.detector_scores``). Nothing is re-run or written.

    python scripts/deploy_intervals.py DEPLOY_DIR [DEPLOY_DIR ...] [--intervals 0 60 120 300]
        [--truth GROUND_TRUTH] [--methods policy sumo_default] [--runs 1]

Interval 0 is the detectors' own (deploy_summary.csv's figures at ``compare_interval_s = 0``).
Measured 2026-11-26 on highway_bremen (docs/deploy-log.md, "Comparison interval (stop 26)").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

from macromicro_sumo.deploy.compare import (
    comparison_table,
    detector_scores,
    read_outputs,
    truth_geometry,
)
from macromicro_sumo.deploy.intervals import block_factor, interval_length_s


def folder_scores(
    folder: Path, truth_dir: Path, methods: list[str], intervals: list[float], runs: list[int]
) -> list[dict]:
    """Rows of (folder, method, interval, scores) of one deploy folder."""
    geometry = truth_geometry(truth_dir)
    truth = read_outputs(truth_dir, geometry, leaders=False)
    period = interval_length_s(truth.detectors)
    rows = []
    for method in methods:
        out = read_outputs(folder / method, geometry, leaders=False)
        for interval in intervals:
            k = block_factor(interval, period, str(truth_dir / "detectors.csv"))
            comp = comparison_table(truth.stations_at(k), out.stations_at(k), method)
            if runs:
                comp = comp[comp["run"].isin(runs)]
            s = detector_scores(comp)
            rows.append(
                {
                    "folder": folder.name,
                    "method": method,
                    "interval_s": k * period,
                    "station_intervals": s["station_intervals"],
                    "geh_below_5": s["share_geh_below_5"],
                    "speed_within_5pct": s["share_speed_within_5pct"],
                    "speed_rmse_mps": s["speed_rmse_mps"],
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", type=Path, nargs="+")
    ap.add_argument("--intervals", type=float, nargs="+", default=[0.0, 60.0, 120.0, 300.0])
    ap.add_argument("--truth", type=Path, default=None, help="default: the manifest's")
    ap.add_argument("--methods", nargs="*", default=None, help="default: the manifest's")
    ap.add_argument("--runs", type=int, nargs="*", default=[], help="only these runs")
    args = ap.parse_args()
    rows = []
    for folder in args.folders:
        manifest = json.loads((folder / "deploy_manifest.json").read_text())
        truth = args.truth or Path(manifest["ground_truth"])
        methods = args.methods or list(manifest["methods"])
        rows += folder_scores(folder, truth, methods, args.intervals, args.runs)
    print(pd.DataFrame(rows).round(3).to_string(index=False))


if __name__ == "__main__":
    main()

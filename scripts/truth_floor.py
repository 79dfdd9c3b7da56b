"""Truth against truth: one ground-truth run's stations scored as a method against another
run's, the ceiling of any population model where the phase of a wave or platoon is chance.

Run j's stations are relabelled as run i and scored with ``deploy.compare``'s own code
(``comparison_table``, ``detector_scores``: GEH < 5, speed within 5%, speed RMSE, bias) at
the comparison interval (default: the scenario's ``deploy.compare_interval_s``), over the
consecutive pairs of the runs listed, cyclically: (r0, r1), (r1, r2), ..., (r_last, r0).
A model that has every driver's population right but its drivers and phase by chance scores
about this. Printed per pair and pooled; ``--out`` writes the pooled and per-pair rows (CSV).

    .venv/bin/python scripts/truth_floor.py SCENARIO.toml RUN_DIR/ground_truth \\
        [--runs 30 31 ...] [--interval 300] [--out floor.csv]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from macromicro_sumo.deploy.compare import (
    HEADLINE_SCORES,
    comparison_table,
    detector_scores,
    read_table,
)
from macromicro_sumo.deploy.intervals import block_factor, interval_length_s, pool_detectors
from macromicro_sumo.deploy.stations import station_table
from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.load import load_scenario

SHOWN = ("pair", *HEADLINE_SCORES)


def get_options(args: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", type=Path, help="the truth's scenario TOML (its interval)")
    p.add_argument("truth", type=Path, help="a ground_truth folder (detectors.csv)")
    p.add_argument("--runs", nargs="+", type=int, default=None, help="runs (default: all)")
    p.add_argument(
        "--interval", type=float, default=None, help="comparison interval [s] (default: scenario)"
    )
    p.add_argument("--out", type=Path, default=None, help="a CSV to write (must not exist)")
    return p.parse_args(args)


def pairs(runs: list[int]) -> list[tuple[int, int]]:
    """The consecutive pairs of ``runs``, cyclically (truth run, run scored as the method)."""
    if len(runs) < 2:
        raise UserError(f"--runs {runs}: accepted: at least two runs of the ground truth")
    return [(runs[i], runs[(i + 1) % len(runs)]) for i in range(len(runs))]


def truth_floor(truth_dir: Path, interval_s: float, runs: list[int] | None = None) -> pd.DataFrame:
    """Per pair (truth run i, run j as the method) and pooled (``pair == "all"``): the
    detector scores of run j's stations against run i's at ``interval_s`` (0: the
    detectors' own)."""
    det = read_table(truth_dir, "detectors.csv")
    where = str(truth_dir / "detectors.csv")
    if det.empty:
        raise UserError(f"{where}: no detector interval")
    have = sorted(int(r) for r in det["run"].unique())
    runs = runs or have
    missing = sorted(set(runs) - set(have))
    if missing:
        raise UserError(f"--runs: {missing} not in {where}; accepted: {have[0]}..{have[-1]}")
    k = block_factor(interval_s, interval_length_s(det), where)
    stations = station_table(det) if k == 1 else station_table(pool_detectors(det, k))
    tables, rows = [], []
    for i, j in pairs(runs):
        truth = stations[stations["run"] == i]
        other = stations[stations["run"] == j].assign(run=i)  # matched on run i's keys
        comp = comparison_table(truth, other, f"run {j}")
        if comp.empty:
            raise UserError(f"{where}: runs {i} and {j} have no station-interval in common")
        tables.append(comp)
        rows.append({"pair": f"{i}-{j}", **detector_scores(comp)})
    pooled = pd.concat(tables, ignore_index=True)
    rows.append({"pair": "all", **detector_scores(pooled)})
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> int:
    options = get_options(argv)
    try:
        if options.out is not None and options.out.exists():
            raise UserError(f"{options.out}: exists; give a new file")
        interval = options.interval
        if interval is None:
            interval = load_scenario(options.scenario).deploy.compare_interval_s
        table = truth_floor(options.truth, interval, options.runs)
    except UserError as e:
        print(f"truth_floor: {e}", file=sys.stderr)
        return 2
    if options.out is not None:
        table.to_csv(options.out, index=False)
    print(table[list(SHOWN)].round(3).to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

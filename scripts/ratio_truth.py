"""The observed drivers' desired-speed ratio estimates against their true speedFactors: a
diagnostic that reads the truth (never a method). Re-runs each of the truth's SUMO runs with
its seed (``runs.csv``) to read every vehicle's speedFactor, then prints, over the train + val
runs, the quantiles (p10 p25 p50 p75 p90, each over the median, and the median) of: every
vehicle seen on the section (the population), the observed vehicles, those with an exact
ratio (cruised freely, ``env.observed_drivers``), those with a lower bound, and the estimates
``policy.driver_ratios`` "kaplan_meier" and "reached" (``env.driver_speed_ratios``).

Why: drawn 522's deployed drivers are slow downstream of its lane drop (stop 49, hM49); this
tells whether the estimate or the observed sample is off (stop 50, hM50: the free drivers
are the slow ones, 522's observed sample is itself slow in its lower tail).

    .venv/bin/python scripts/ratio_truth.py SCENARIO.toml GROUND_TRUTH [--csv OUT]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import libsumo
import numpy as np
import pandas as pd
import sumolib

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.env.driver_speed_ratios import QUANTILE_LEVELS, ratio_estimate
from macromicro_sumo.env.observed_drivers import observed_drivers
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

LEVELS = (0.1, 0.25, 0.5, 0.75, 0.9)


def true_factors(sc, gt: Path) -> pd.DataFrame:
    """(run, vehicle_id, true_factor) of every vehicle the truth's runs insert (SUMO re-run
    with each run's seed and the run's detectors, as recorded)."""
    rows = []
    runs = pd.read_csv(gt / "runs.csv")
    routes = ",".join(str(p) for p in sc.network.route_files)
    end = sc.simulation.warmup_s + sc.simulation.duration_s
    with tempfile.TemporaryDirectory(prefix="ratio_truth_") as tmp:
        for run, seed in zip(runs["run"], runs["sumo_seed"], strict=True):
            adds = Path(tmp) / f"detectors_{int(run)}.add.xml"
            shutil.copy(gt / "sumo" / f"run_{int(run):03d}" / "detectors.add.xml", adds)
            libsumo.start(
                [sumolib.checkBinary("sumo"), "-n", str(sc.network.net_file), "-r", routes,
                 "-a", str(adds), "--step-length", repr(sc.simulation.step_length_s),
                 "--seed", str(int(seed)), "--collision.action", "warn", "--no-step-log",
                 "true", "--duration-log.disable", "true", "--no-warnings", "true"]
            )  # fmt: skip
            try:
                while libsumo.simulation.getTime() < end:
                    libsumo.simulationStep()
                    for v in libsumo.simulation.getDepartedIDList():
                        rows.append((int(run), v, libsumo.vehicle.getSpeedFactor(v)))
            finally:
                libsumo.close()
    return pd.DataFrame(rows, columns=["run", "vehicle_id", "true_factor"])


def row(name: str, quantiles: np.ndarray, n: int) -> dict[str, object]:
    """One table row: ``quantiles`` at ``QUANTILE_LEVELS`` read at ``LEVELS``."""
    median = float(np.interp(0.5, QUANTILE_LEVELS, quantiles))
    at = np.interp(LEVELS, QUANTILE_LEVELS, quantiles) / median
    return {"what": name, "n": n, "median": median, **{f"p{round(100 * q)}/med": a for q, a in zip(LEVELS, at, strict=True)}}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", type=Path)
    p.add_argument("ground_truth", type=Path)
    p.add_argument("--csv", type=Path, help="also write the table here")
    args = p.parse_args(argv)
    sc = load_scenario(args.scenario)
    truth = load_section_truth(args.ground_truth, sc)
    s = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    runs = np.concatenate([s["train"], s["val"]])
    tf = true_factors(sc, args.ground_truth)
    factor = {(r, str(v)): f for r, v, f in tf.itertuples(index=False)}
    seen = truth.trajectories[truth.trajectories["run"].isin(runs)]
    keys = [(int(r), str(v)) for r, v in seen.groupby(["run", "vehicle_id"]).size().index]
    missing = [k for k in keys if k not in factor]
    if missing:
        print(f"ratio_truth.py: {len(missing)} vehicles of the truth not re-run (first {missing[0]}): "
              "the re-run does not reproduce the truth", file=sys.stderr)  # fmt: skip
        return 1
    d = observed_drivers(sc, truth, runs)

    def truth_row(name: str, ks: list) -> dict[str, object]:
        x = np.array([factor[k] for k in ks])
        return row(name, np.quantile(x, QUANTILE_LEVELS), len(x))

    rows = [
        truth_row("true: every vehicle seen", keys),
        truth_row("true: observed", [*d.ratio, *d.lower]),
        truth_row("true: exact ratio (free)", list(d.ratio)),
        truth_row("true: lower bound", list(d.lower)),
    ]
    for censoring in ("kaplan_meier", "reached"):
        e = ratio_estimate(d, censoring)
        rows.append(row(f"estimate {censoring}", e.quantiles, e.exact))
    table = pd.DataFrame(rows).set_index("what")
    print(f"{args.scenario.stem}: train + val runs {sorted(runs.tolist())}")
    print(table.round(3).to_string())
    if args.csv:
        table.to_csv(args.csv)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Deploy a finished run's policy prior alone (the residual at 0) on its held-out runs, beside
the methods the run deployed: is a loss the prior's or the learned residual's?

The policy's checkpoint with ``residual_bound`` set to 0 drives every population vehicle as
the deployment does (``deploy.run.run_method``: the safety layer, each driver's speed
factor), with the floor the run's ``policy`` deployment chose (``deploy/policy/
manifest.json``), so that only the residual differs. Written into ``--out`` (default
``RUN/prior_alone``): ``prior_alone/`` (the method's folder, without SUMO's files),
``deploy_comparison.csv`` and ``deploy_summary.csv`` of the run's methods and
``prior_alone`` against the ground truth (``deploy.compare.compare_folders``); the summary's
speed figures are printed. Measured use: docs/deploy-log.md, the untuned networks at stop 34.

    .venv/bin/python scripts/deploy_prior_alone.py SCENARIO.toml RUN_DIR
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import pandas as pd
import torch

from macromicro_sumo.deploy.compare import compare_folders
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.deploy.population import population_scenario
from macromicro_sumo.deploy.run import Drive, load_context, run_method, write_method
from macromicro_sumo.errors import UserError
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.scenario.load import load_scenario

METHOD = "prior_alone"
SHOWN = (
    "method",
    "station_intervals",
    "share_geh_below_5",
    "share_speed_within_5pct",
    "speed_rmse_mps",
    "speed_bias_mps",
    "collisions",
    "teleports",
    "safety_acted_share",
    "floor_acted_share",
)


def get_options(args: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", type=Path, help="the run's scenario TOML")
    p.add_argument("run", type=Path, help="a finished `macromicro run` folder")
    p.add_argument("--out", type=Path, default=None, help="output folder (RUN/prior_alone)")
    return p.parse_args(args)


def policy_floor(run: Path) -> str:
    """The floor the run's ``policy`` deployment drove with (``safety_floor_on``)."""
    path = run / "deploy" / "policy" / "manifest.json"
    if not path.is_file():
        raise UserError(f"{path}: not found; deploy the policy first (deploy.methods)")
    return str(json.loads(path.read_text())["safety_floor_on"])


def deploy_prior_alone(scenario: Path, run: Path, out: Path) -> pd.DataFrame:
    """The prior alone deployed into ``out / METHOD``; the summary of every method."""
    sc = load_scenario(scenario)
    truth = run / "ground_truth"
    floor = policy_floor(run)
    agent = load_policy(run / "policy" / "policy.pt", sc, sc.deploy.speed_level)
    with torch.no_grad():
        agent.residual_bound.fill_(0.0)  # policy_batch: the fitted prior alone
    ctx = load_context(sc, truth)
    ctx.sc = population_scenario(ctx.sc)  # as the deployment's drivers read it
    torch.set_num_threads(1)
    shutil.rmtree(out, ignore_errors=True)
    folder = out / METHOD
    folder.mkdir(parents=True)
    t0 = time.perf_counter()
    drive = Drive(act=policy_batch(agent), safety=sc.deploy.safety, floor_on=floor)
    res = run_method(ctx, drive, folder)
    wall = round(time.perf_counter() - t0, 1)
    write_method(ctx, res, folder, {"method": METHOD, "safety_floor_on": floor, "wall_s": wall})
    shutil.rmtree(folder / "sumo", ignore_errors=True)
    dirs = {m: run / "deploy" / m for m in sc.deploy.methods}
    dirs[METHOD] = folder
    comparison, summary = compare_folders(truth, dirs, sc.deploy.compare_interval_s)
    comparison.to_csv(out / "deploy_comparison.csv", index=False)
    summary.to_csv(out / "deploy_summary.csv", index=False)
    print(f"{METHOD}: held-out runs {ctx.held_out}, floor {floor}, {wall} s")
    return summary


def main(options: argparse.Namespace) -> None:
    out = options.out or options.run / METHOD
    summary = deploy_prior_alone(options.scenario, options.run, out)
    print(summary[[c for c in SHOWN if c in summary]].round(3).to_string(index=False))


if __name__ == "__main__":
    main(get_options())

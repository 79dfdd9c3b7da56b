"""Deploy a finished run's methods on chosen runs of its ground truth (default: every run),
to measure a change on more than the one held-out run ``macromicro run`` deploys.

Each method drives as the deploy stage drives it (``deploy.stage.method_drive``; the floor
chosen on the training runs where ``deploy.safety_floor_on = "auto"``); ``--set`` changes a
``[deploy]`` or ``[policy]`` key of the scenario for this deployment only (what a change
under test is switched by). Written into ``--out`` (a new or empty folder): a folder per
method (without SUMO's files), ``deploy_comparison.csv`` and ``deploy_summary.csv`` against
the ground truth over the runs deployed, and ``deploy_runs.csv``, each run's safety counts
and station scores per method (``deploy.compare.detector_scores``: the station rows, not
the per-lane ones). The runs' figures in docs/deploy.md ("all 4 runs") are this.
``idm_detectors`` drives with the IDM the run's deploy stage fitted to the detectors (its
``deploy/idm_detectors/manifest.json``'s ``theta``), not fitted again.

    .venv/bin/python scripts/deploy_runs.py SCENARIO.toml RUN_DIR --out DIR \\
        [--methods policy sumo_default] [--runs 0 1] [--set deploy.merge_reach=occupation]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import pandas as pd
import torch

from macromicro_sumo.deploy.compare import HEADLINE_SCORES, compare_folders, detector_scores
from macromicro_sumo.deploy.floor_choice import resolve_floor
from macromicro_sumo.deploy.population import population_scenario
from macromicro_sumo.deploy.run import load_context, run_method, write_method
from macromicro_sumo.deploy.stage import fit_idm, method_drive, policy_paths
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import read_manifest
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

SHOWN = ("method", *HEADLINE_SCORES, "collisions", "teleports", "emergency_brakings")
PER_RUN = ("collisions", "teleports", "emergency_brakings")


def get_options(args: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", type=Path, help="the run's scenario TOML")
    p.add_argument("run", type=Path, help="a finished `macromicro run` folder")
    p.add_argument("--out", type=Path, required=True, help="a new or empty output folder")
    p.add_argument("--methods", nargs="+", default=["policy"], help="deploy methods")
    p.add_argument("--runs", nargs="+", type=int, default=None, help="runs (default: all)")
    p.add_argument("--set", nargs="*", default=[], metavar="TABLE.KEY=VALUE", dest="changes")
    return p.parse_args(args)


def _number(text: str) -> bool:
    """Whether ``text`` reads as a number (a field of ``float | str``, deploy.command_dawdle,
    takes a word too)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def changed(sc, changes: list[str]):
    """``sc``'s file loaded again with each ``deploy.KEY=VALUE`` / ``policy.KEY=VALUE`` set
    (typed as the field), so that the scenario's own checks (ranges, choices,
    ``check_deploy``) and its load-time defaults (``deploy.merge_reach`` under merge none or
    handover) apply to them: set on the loaded dataclasses, a value outside the choices
    (``deploy.merge_reach=always``) was deployed as whatever the driver made of it."""
    overrides = {}
    for item in changes:
        key, _, text = item.partition("=")
        table, _, name = key.partition(".")
        if table not in ("deploy", "policy") or not hasattr(getattr(sc, table), name):
            raise UserError(f"--set {item}: accepted: deploy.KEY=VALUE or policy.KEY=VALUE")
        old = getattr(getattr(sc, table), name)
        if isinstance(old, bool):
            value = {"true": True, "false": False}.get(text.lower(), text)
        elif _number(text):
            value = float(text)
            value = int(value) if isinstance(old, int) and value.is_integer() else value
        else:
            value = text
        overrides[key] = value
    return load_scenario(sc.source, overrides) if overrides else sc


def prepared(
    scenario: Path,
    run: Path,
    changes: list[str],
    methods: list[str],
    runs: list[int] | None,
    out: Path,
):
    """(scenario with ``changes``, deploy context, runs (default: every run of the truth),
    the learned methods' agents) of a finished ``run``, as the deploy stage prepares them;
    ``out`` must be new or empty (also scripts/classify_brakings.py's)."""
    sc = changed(load_scenario(scenario), changes)
    if out.exists() and any(out.iterdir()):
        raise UserError(f"{out}: not empty; give a new folder")
    truth_dir = run / "ground_truth"
    runs = runs or [int(r) for r in load_section_truth(truth_dir, sc).runs]
    paths = policy_paths(run / "policy", methods)
    agents = {name: load_policy(p, sc, sc.deploy.speed_level) for name, p in paths.items()}
    ctx = load_context(sc, truth_dir)
    ctx.sc = population_scenario(ctx.sc)  # as the deploy stage's drivers read it
    return sc, ctx, runs, agents


def detector_theta(run: Path) -> dict[str, float]:
    """The IDM vType parameters the deploy stage of ``run`` fitted to the detectors (what
    ``idm_detectors`` drives with). Without them method_drive's theta is None, which drives
    the truth's own vTypes: the oracle under another name."""
    path = run / "deploy" / "idm_detectors" / "manifest.json"
    if not path.is_file():
        raise UserError(
            f"{path}: missing; idm_detectors needs the run's deploy stage to have fitted it "
            "(deploy.methods with idm_detectors), or leave it out of --methods"
        )
    theta = read_manifest(path).get("theta")
    if not isinstance(theta, dict) or not theta:
        raise UserError(f"{path}: theta: missing or empty; accepted: the fitted IDM parameters")
    return {str(k): float(v) for k, v in theta.items()}


def deploy_runs(options: argparse.Namespace) -> pd.DataFrame:
    """Every method of ``options`` deployed on its runs; the summary of them all."""
    out = options.out
    fitted = detector_theta(options.run) if "idm_detectors" in options.methods else None
    sc, ctx, runs, agents = prepared(
        options.scenario, options.run, options.changes, options.methods, options.runs, out
    )
    truth_dir = ctx.truth_dir
    idm = fit_idm(ctx)[0] if "idm_calibrated" in options.methods else None
    torch.set_num_threads(1)
    dirs, per_run = {}, []
    for name in options.methods:
        t0 = time.perf_counter()
        drive, record = method_drive(name, sc, agents, idm, fitted)
        drive, _ = resolve_floor(ctx, drive, out / "floor_choice")
        shutil.rmtree(out / "floor_choice", ignore_errors=True)
        folder = out / name
        folder.mkdir(parents=True)
        res = run_method(ctx, drive, folder, runs=runs)
        wall = round(time.perf_counter() - t0, 1)
        write_method(ctx, res, folder, {"method": name, "runs": runs, "wall_s": wall, **record})
        shutil.rmtree(folder / "sumo", ignore_errors=True)
        dirs[name] = folder
        per_run.append(res.runs[["run", *PER_RUN]].assign(method=name))
        print(f"{name}: runs {runs}, {wall} s", flush=True)
    comparison, summary = compare_folders(truth_dir, dirs, sc.deploy.compare_interval_s)
    comparison.to_csv(out / "deploy_comparison.csv", index=False)
    summary.to_csv(out / "deploy_summary.csv", index=False)
    # Per run, the summary's own scores (station rows only, not the per-lane ones).
    scores = pd.DataFrame(
        [
            {"method": m, "run": r, **{k: detector_scores(g)[k] for k in HEADLINE_SCORES}}
            for (m, r), g in comparison.groupby(["method", "run"])
        ]
    )
    pd.concat(per_run).merge(scores, on=["method", "run"], how="left").to_csv(
        out / "deploy_runs.csv", index=False
    )
    return summary


def main(argv: list[str] | None = None) -> int:
    try:
        summary = deploy_runs(get_options(argv))
    except UserError as e:
        print(f"deploy_runs: {e}", file=sys.stderr)
        return 2
    print(summary[[c for c in SHOWN if c in summary]].round(3).to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The ``macromicro`` command line: one subcommand per pipeline stage.

``main(argv)`` parses, runs and returns an exit code, so tests call it without a
subprocess. Bad input surfaces as one ``error:`` line and exit code 2, never a traceback.
Each subcommand loads the scenario and calls its stage function.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

from macromicro_sumo.batch import runner as batch
from macromicro_sumo.env.examples import example_names, example_scenario, sumo_nets_dir
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import check_out_path
from macromicro_sumo.generator.complete import run_complete
from macromicro_sumo.pipeline import stages
from macromicro_sumo.pipeline.build import policy_paths
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo import simulation as sumo
from macromicro_sumo.sumo.inputs import input_files
from macromicro_sumo.sumo.versions import versions


def _scenario(args: argparse.Namespace) -> Any:
    """The scenario of ``args``, with ``--out`` checked against every file it reads."""
    example = getattr(args, "example", None)
    if example is not None and args.scenario is not None:
        raise UserError(f"give a scenario file or --example {example}, not both")
    if example is not None:
        args.scenario = example_scenario(example)
    elif args.scenario is None:
        raise UserError(
            "a scenario is needed: a TOML file, or --example NAME for a shipped one "
            f"({', '.join(example_names())})"
        )
    sc = load_scenario(args.scenario)
    check_out_path(args.out, [args.scenario, *input_files(sc)])
    return sc


def _cmd_simulate(args: argparse.Namespace) -> int:
    out = stages.simulate(_scenario(args), args.out, args.command_line, not args.quiet)
    print(f"ground truth written to {out}")
    return 0


def _cmd_train_generator(args: argparse.Namespace) -> int:
    sc = _scenario(args)
    m = stages.train_generator(sc, args.data, args.out, args.command_line, not args.quiet)
    print(
        f"generator written to {args.out / 'generator.pt'} ({m['epochs']} epochs, {m['timings_s']['train_generator']:.1f} s)"
    )
    return 0


def _cmd_complete(args: argparse.Namespace) -> int:
    sc = _scenario(args)
    m = run_complete(
        sc,
        args.generator,
        args.data,
        args.out,
        args.snapshot,
        args.hidden,
        args.completions,
        args.seed,
        args.command_line,
    )
    print(
        f"{m['scenes']} scene(s) x {m['completions']} completion(s), hidden counts "
        f"{m['hidden_counts']}, written to {args.out / 'completions.csv'}"
    )
    return 0


def _cmd_train_policy(args: argparse.Namespace) -> int:
    sc = _scenario(args)
    m = stages.train_policy(
        sc, args.data, args.generator, args.out, args.resume, args.command_line, not args.quiet
    )
    print(f"policy written to {args.out / 'policy.pt'} ({m['timings_s']['train_policy']:.1f} s)")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    sc = _scenario(args)
    policies = (
        policy_paths(args.policy.parent)
        if args.policy.name == "policy.pt"
        else {"policy": args.policy}
    )
    policies["policy"] = args.policy
    stages.evaluate(
        sc,
        args.data,
        args.generator,
        policies,
        args.out,
        args.command_line,
        not args.quiet,
        args.hidden,
    )
    print(f"evaluation written to {args.out}")
    return 0


def _deploy_inputs(policy: Path, data: Path | None) -> tuple[Path, Path]:
    """(ground-truth folder, policy folder) from --policy (a finished ``macromicro run``
    folder, a policy folder or a policy.pt) and --data (default: the run's ground_truth)."""
    if policy.is_file():
        pol = policy.parent
    elif (policy / "policy").is_dir():
        pol = policy / "policy"
    elif policy.is_dir():
        pol = policy
    else:
        raise UserError(
            f"--policy {policy}: not found; pass a finished `macromicro run` folder, a policy "
            "folder or its policy.pt"
        )
    if data is None:
        for cand in (pol.parent / "ground_truth", policy / "ground_truth"):
            if (cand / "manifest.json").is_file():
                data = cand
                break
    if data is None:
        raise UserError(
            f"--policy {policy}: no ground_truth folder beside it; pass --data GROUND_TRUTH"
        )
    return data, pol


def _cmd_deploy(args: argparse.Namespace) -> int:
    sc = _scenario(args)
    data, pol = _deploy_inputs(args.policy, args.data)
    check_out_path(args.out, [data, pol])
    m = stages.deploy(
        sc, data, pol, args.out, args.command_line, not args.quiet, args.methods or None
    )
    width = max(map(len, m["totals"]), default=0)
    for name, t in m["totals"].items():
        print(
            f"{name:>{width}}: {t['collisions']} collisions, {t['teleports']} teleports, "
            f"{t['vehicle_steps_driven']} vehicle-steps driven, safety acted {t['safety_acted']}"
        )
    print(f"deployment written to {args.out}")
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    stages.run(_scenario(args), args.out, args.command_line, progress=not args.quiet)
    print(f"pipeline outputs in {args.out}")
    return 0


def _cmd_doctor(args: argparse.Namespace) -> int:
    root = sumo_nets_dir()  # shipped with the package (package data), as the examples
    info = versions()
    print(f"SUMO binary : {info['sumo_binary']}")
    print(f"SUMO        : {info['sumo']}")
    print(f"libsumo     : {info['libsumo']}")
    version = sumo.quick_check(root / "ring_r100_e4.net.xml", root / "ring_r100_e4.add.xml")
    print(f"one-second SUMO run through libsumo: ok ({version})")
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse with its usage errors on one ``error:`` line, as every other bad input
    (README, Bad input), instead of the usage block and a second line; exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {self.prog}: {message}; see {self.prog} --help\n")


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(
        prog="macromicro",
        description="Learn a driving policy in SUMO that matches the observed vehicles and "
        "the detectors, and deploy it: one subcommand per pipeline stage.",
    )
    sub = ap.add_subparsers(dest="command", required=True)

    def add(
        name: str, func: Callable[[argparse.Namespace], int], help: str
    ) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help, description=help)
        p.set_defaults(func=func)
        p.add_argument("--quiet", action="store_true", help="no progress bars")
        return p

    def scenario_or_example(p: argparse.ArgumentParser) -> None:
        p.add_argument("scenario", type=Path, nargs="?", help="scenario TOML (or --example)")
        p.add_argument(
            "--example",
            metavar="NAME",
            help="a scenario shipped with the package instead of a file: "
            + ", ".join(example_names()),
        )

    p = add(
        "simulate", _cmd_simulate, "ground-truth SUMO runs with loop detectors and macro statistics"
    )
    scenario_or_example(p)
    p.add_argument("--out", type=Path, required=True, help="output folder")

    p = add(
        "run",
        _cmd_run,
        "the whole pipeline: ground truth, generator, policies, evaluation, deployment, report "
        "(each stage redone only when its settings or an earlier stage changed)",
    )
    scenario_or_example(p)
    p.add_argument("--out", type=Path, required=True, help="output folder")

    p = add("train-generator", _cmd_train_generator, "Stage I: train the hidden-vehicle generator")
    p.add_argument("scenario", type=Path, help="scenario TOML")
    p.add_argument("--data", type=Path, required=True, help="ground-truth folder (from simulate)")
    p.add_argument("--out", type=Path, required=True, help="output folder")

    p = add(
        "train-policy", _cmd_train_policy, "Stage II: PPO for the shared policy (micro + eta macro)"
    )
    p.add_argument("scenario", type=Path, help="scenario TOML")
    p.add_argument("--data", type=Path, required=True, help="ground-truth folder (from simulate)")
    p.add_argument("--generator", type=Path, required=True, help="generator.pt")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument(
        "--resume", action="store_true", help="continue from the last checkpoint in --out"
    )

    p = add(
        "evaluate", _cmd_evaluate, "macro alignment, micro consistency and leader-follower tests"
    )
    p.add_argument("scenario", type=Path, help="scenario TOML")
    p.add_argument("--data", type=Path, required=True, help="ground-truth folder (from simulate)")
    p.add_argument("--generator", type=Path, required=True, help="generator.pt")
    p.add_argument(
        "--policy", type=Path, required=True, help="policy.pt (ablations beside it are used too)"
    )
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument(
        "--hidden",
        type=int,
        nargs="+",
        metavar="K",
        help="only the held-out scenes hiding K vehicles (default: every scene)",
    )

    p = add(
        "deploy",
        _cmd_deploy,
        "Stage III: every method driving the held-out runs' whole demand in SUMO",
    )
    p.add_argument("scenario", type=Path, help="scenario TOML")
    p.add_argument(
        "--policy",
        type=Path,
        required=True,
        help="a finished `macromicro run` folder, a policy folder, or its policy.pt",
    )
    p.add_argument(
        "--data", type=Path, help="ground-truth folder (default: the run folder's ground_truth)"
    )
    p.add_argument("--out", type=Path, required=True, help="output folder (one folder per method)")
    p.add_argument(
        "--methods", nargs="+", help="methods to deploy (default: the scenario's deploy.methods)"
    )

    p = add(
        "complete",
        _cmd_complete,
        "Stage I alone: complete partly observed scenes with a trained generator (CSV)",
    )
    p.add_argument("scenario", type=Path, help="scenario TOML")
    p.add_argument("--generator", type=Path, required=True, help="generator.pt")
    p.add_argument(
        "--data", type=Path, required=True, help="ground-truth folder (its detectors give psi)"
    )
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument(
        "--snapshot",
        metavar="CSV|RUN:TIME",
        help="a CSV of observed vehicles, or one snapshot of the ground truth "
        "(default: every held-out snapshot)",
    )
    p.add_argument(
        "--hidden",
        type=int,
        nargs="+",
        metavar="K",
        help="hidden counts: the scenes hiding K (ground truth), or K to place (a CSV)",
    )
    p.add_argument(
        "--completions", type=int, default=1, help="completions per scene (seeded seed + c)"
    )
    p.add_argument("--seed", type=int, help="first completion's seed (default: the scenario's)")

    add(
        "doctor",
        _cmd_doctor,
        "which SUMO and libsumo are in use, and whether a one-second run works",
    )
    batch.register(sub)  # batch and export
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.command_line = "macromicro " + shlex.join(argv)
    try:
        return int(args.func(args))
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(
            "interrupted: finished outputs are intact, unfinished ones were not written",
            file=sys.stderr,
        )
        return 130


if __name__ == "__main__":
    raise SystemExit(main())

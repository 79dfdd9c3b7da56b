"""A tiny single pass (the generator, then the policy) on a ground truth, for the joint
refinement's tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from conftest import write_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.policy.stage import run_train_policy
from macromicro_sumo.scenario.load import load_scenario


def tiny_single_pass(folder: Path, gt: Path, overrides: dict[str, Any]) -> tuple[Any, Path, Path]:
    """(scenario, generator.pt, policy.pt) of the scenario with ``overrides`` written into
    ``folder``, its generator trained by the CLI on ``gt`` and its policy by the policy
    stage with the pipeline's prior fit."""
    path = write_scenario(folder, overrides)
    gen = folder / "generator"
    args = ["train-generator", str(path), "--data", str(gt), "--out", str(gen)]
    assert main([*args, "--quiet"]) == 0
    sc = load_scenario(path)
    pol = folder / "policy"
    run_train_policy(
        sc, gt, gen / "generator.pt", pol, progress=False, fit_prior=fit_residual_prior
    )
    return sc, gen / "generator.pt", pol / "policy.pt"

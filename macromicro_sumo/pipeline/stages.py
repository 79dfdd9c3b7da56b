"""Each stage as one function for every scenario (a section of a network, the paper's ring
among them): what the command line and batch runs call.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

from macromicro_sumo.deploy.stage import deploy as deploy_stage
from macromicro_sumo.files import writer_session
from macromicro_sumo.pipeline.build import SECTION, run_pipeline
from macromicro_sumo.policy.stage import run_train_policy
from macromicro_sumo.report.deploy import make_deploy_plots


def _one_writer(stage: Callable[..., Any]) -> Callable[..., Any]:
    """The stage holds the lock of every output folder it prepares until it returns."""

    @functools.wraps(stage)
    def locked(*args: Any, **kwargs: Any) -> Any:
        with writer_session():
            return stage(*args, **kwargs)

    return locked


@_one_writer
def simulate(sc: Any, out: Path | str, command: str = "", progress: bool = True) -> Path:
    """Ground truth: the scenario's demand in SUMO, recorded with detectors."""
    return SECTION.simulate(sc, out, command, progress)


@_one_writer
def train_generator(
    sc: Any, data: Path, out: Path, command: str = "", progress: bool = True
) -> dict[str, Any]:
    """Stage I: the hidden-vehicle generator, trained on the ground truth in ``data``."""
    return SECTION.train_generator(sc, data, out, command, progress)


@_one_writer
def train_policy(
    sc: Any,
    data: Path,
    generator: Path,
    out: Path,
    resume: bool | str = False,
    command: str = "",
    progress: bool = True,
) -> dict[str, Any]:
    """Stage II: the shared policy, trained with PPO on micro + eta macro."""
    fit = SECTION.fit_prior
    return run_train_policy(sc, data, generator, out, resume, command, progress, fit_prior=fit)


@_one_writer
def evaluate(
    sc: Any,
    data: Path,
    generator: Path,
    policies: dict[str, Path],
    out: Path,
    command: str = "",
    progress: bool = True,
    hidden: list[int] | None = None,
) -> Any:
    """Every method on the held-out runs (``hidden``: only the scenes hiding those K)."""
    return SECTION.evaluate(sc, data, generator, policies, out, command, progress, hidden)


@_one_writer
def deploy(
    sc: Any,
    data: Path,
    policy: Path | None,
    out: Path,
    command: str = "",
    progress: bool = True,
    methods: list[str] | None = None,
) -> dict[str, Any]:
    """Stage III: every method over the held-out runs' whole demand, in ``out/<method>``."""
    return deploy_stage(sc, data, policy, out, command, progress, methods, make_deploy_plots)


@_one_writer
def run(sc: Any, out: Path | str, command: str = "", progress: bool = True) -> dict[str, Any]:
    """The whole pipeline, stage by stage; stages whose inputs did not change are reused."""
    return run_pipeline(sc, SECTION, out, command, progress)

"""Each stage as one function for every scenario (a section of a network, the paper's ring
among them), holding the lock of every output folder it prepares until it returns: what the
command line and batch runs call.
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


simulate = _one_writer(SECTION.simulate)
train_generator = _one_writer(SECTION.train_generator)
train_policy = _one_writer(
    functools.partial(
        run_train_policy, fit_prior=SECTION.fit_prior, score_prior=SECTION.score_prior
    )
)
evaluate = _one_writer(SECTION.evaluate)
deploy = _one_writer(functools.partial(deploy_stage, plots=make_deploy_plots))


@_one_writer
def run(sc: Any, out: Path | str, command: str = "", progress: bool = True) -> dict[str, Any]:
    """The whole pipeline, stage by stage; stages whose inputs did not change are reused."""
    return run_pipeline(sc, SECTION, out, command, progress)

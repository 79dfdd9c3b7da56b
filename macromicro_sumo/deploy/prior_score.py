"""A candidate prior deployed alone on the training runs: the project's one prior-alone scorer.

``policy.prior_choice`` fits every prior family to the observed pairs and keeps the one
whose prior alone (the residual at 0) drives the training runs' demand closest to the
truth; ``policy.relax_choice`` keeps the Krauss relaxation time (where the pairs leave it
at its bound) the same way. ``deploy_prior`` is that drive: the deployment itself
(``deploy.run.run_method``, its safety layer and driver speeds as the trained policy will
meet them) on the first ``deploy.safety_floor_runs`` training runs (never the held-out runs
the report scores, nor validation: ``deploy.calibrate.training_runs``), scored with the
report's speed RMSE against the truth's detectors there (``deploy.floor_choice.speed_rmse``:
on a simulated truth every interval from SUMO's first step, so the departure the
relaxation shapes counts). Why a deployment and not the demand env Stage II trains on: the
demand env applies the prior's commands without the safety layer, and on drawn net 300
each family's prior alone collided 1,386-1,770 times over the three runs, where deployed
it collided never (docs: "The prior's family chosen (stop 32)"); on drawn net 311 every
relaxation candidate collided 606-906 times there ("One prior-alone scorer (stop 33)").
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pandas as pd

from macromicro_sumo.deploy.compare import truth_reference
from macromicro_sumo.deploy.floor_choice import AUTO, FLOOR_CANDIDATES, choice_runs, speed_rmse
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.deploy.population import population_scenario
from macromicro_sumo.deploy.run import Drive, load_context, run_method
from macromicro_sumo.policy.agent import Agent


def deploy_prior(sc: Any, data: Path | str, agent: Agent) -> dict[str, Any]:
    """``agent`` (a prior alone: ``residual_bound`` 0) deployed on the first
    ``deploy.safety_floor_runs`` training runs of the ground truth in ``data``: its speed
    RMSE [m/s] against the truth's detectors there, per run, and its safety counts. The
    floor is ``deploy.safety_floor_on``'s, "all" where that is "auto" (the choice's tie;
    choosing it per family would deploy each twice). SUMO's files go to a temporary
    folder, removed at once."""
    t0 = time.perf_counter()
    data = Path(data)
    ctx = load_context(sc, data)
    ctx.sc = population_scenario(ctx.sc)  # as the deployment's drivers read it
    runs = choice_runs(ctx, sc.deploy.safety_floor_runs)
    floor = sc.deploy.safety_floor_on
    floor = FLOOR_CANDIDATES[0] if floor == AUTO else floor
    det = pd.read_csv(data / "detectors.csv")
    truth = det[det["run"].isin(runs)].reset_index(drop=True)
    from_s, interval_s = truth_reference(data).from_s, sc.deploy.compare_interval_s
    folder = Path(tempfile.mkdtemp(prefix="prior_choice_"))
    try:
        res = run_method(ctx, replace(Drive(act=policy_batch(agent)), floor_on=floor), folder, runs)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    got = res.detectors
    by_run = {
        str(r): speed_rmse(truth[truth["run"] == r], got[got["run"] == r], interval_s, from_s)
        for r in runs
    }
    return {
        "speed_rmse_mps": speed_rmse(truth, got, interval_s, from_s),
        "speed_rmse_by_run_mps": by_run,
        "runs": runs,
        "safety_floor_on": floor,
        "collisions": int(res.runs["collisions"].sum()),
        "teleports": int(res.runs["teleports"].sum()),
        "wall_s": round(time.perf_counter() - t0, 1),
    }

"""``deploy.safety_floor_on = "auto"``: the safety layer's floor chosen from the training runs.

Which vehicles the floor raises (``deploy.safety``) is a trade-off no fixed default wins
everywhere (docs/deploy-log.md, "Safety layer strictness"): "all" keeps a standing start and a
policy that always brakes moving at a fifth of the limit, "standing" leaves a moving car's
braking in a queue to its policy. "auto" deploys the learned method with each
(``FLOOR_CANDIDATES``) on the first ``deploy.safety_floor_runs`` TRAINING runs of the
ground truth (``deploy.calibrate.training_runs``: never the held-out runs the report scores,
nor validation), scores each against the truth's detectors on those runs with the speed
RMSE the report uses (``deploy.compare``, at ``deploy.compare_interval_s``), and keeps the
lower; a tie (the floor never acted) keeps "all", the fixed default. The choice and both
figures go into the method's manifest (``FloorChoice.record``).
"""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from macromicro_sumo.deploy.calibrate import training_runs
from macromicro_sumo.deploy.compare import (
    comparison_table,
    detector_scores,
    station_table,
    truth_reference,
)
from macromicro_sumo.deploy.intervals import block_factor, interval_length_s, pool_detectors
from macromicro_sumo.deploy.run import DeployContext, Drive, run_method

AUTO = "auto"
# The fixed floors "auto" chooses from; the first wins a tie (the default before "auto").
FLOOR_CANDIDATES: tuple[str, ...] = ("all", "standing")


@dataclass(frozen=True)
class FloorChoice:
    """The floor chosen, each candidate's speed RMSE [m/s] on the training runs ``runs``,
    and the wall time the choice took [s]."""

    chosen: str
    speed_rmse_mps: dict[str, float]
    runs: list[int]
    wall_s: float
    # each candidate's speed RMSE [m/s] per run of ``runs``: how much the runs agree
    by_run_mps: dict[str, dict[int, float]] = dataclasses.field(default_factory=dict)
    # the candidates deployed (the others drive the same runs: "all" raised nothing)
    deployed: tuple[str, ...] = FLOOR_CANDIDATES

    def record(self) -> dict[str, Any]:
        """What a manifest records of the choice."""
        return {
            "option": AUTO,
            "chosen": self.chosen,
            "training_runs": self.runs,
            "speed_rmse_mps": {k: round(v, 6) for k, v in self.speed_rmse_mps.items()},
            "speed_rmse_by_run_mps": {
                k: {str(r): round(v, 6) for r, v in runs.items()}
                for k, runs in self.by_run_mps.items()
            },
            "deployed": list(self.deployed),
            "wall_s": round(self.wall_s, 3),
        }


def needs_choice(sc: Any, drive: Drive) -> bool:
    """Whether ``drive`` is a speed-commanding method whose floor "auto" must choose: its
    commands go through the safety layer (``Drive.safety``, else ``deploy.safety``) with
    a floor (a share above 0: at 0 both candidates are the same deployment)."""
    dep = sc.deploy
    safety = drive.safety or dep.safety
    return (
        drive.act is not None
        and drive.floor_on is None
        and dep.safety_floor_on == AUTO
        and safety == "sumo"
        and dep.safety_floor_share > 0.0
    )


def choice_runs(ctx: DeployContext, n_runs: int) -> list[int]:
    """The first ``n_runs`` training runs (in run order) the choice deploys on."""
    return training_runs(ctx)[:n_runs]


def speed_rmse(
    truth_det: pd.DataFrame, method_det: pd.DataFrame, interval_s: float, from_s: float = 0.0
) -> float:
    """The report's speed RMSE [m/s] (``deploy.compare``'s ``speed_rmse_mps``) of a
    deployment's detectors ``method_det`` against the truth's ``truth_det`` (both in the
    ``detectors.csv`` schema), station-intervals of ``interval_s`` (0: the detectors'
    own) from ``from_s`` on (field data: the end of the warm-up)."""
    k = block_factor(interval_s, interval_length_s(truth_det), "deploy.compare_interval_s")

    def stations(det: pd.DataFrame) -> pd.DataFrame:
        st = station_table(det if k == 1 else pool_detectors(det, k))
        return st[st["begin_s"] >= from_s - 1e-9] if from_s else st

    comp = comparison_table(stations(truth_det), stations(method_det), "floor")
    return float(detector_scores(comp)["speed_rmse_mps"])


def choose_floor(ctx: DeployContext, drive: Drive, scratch: Path, n_runs: int) -> FloorChoice:
    """Deploy ``drive`` with each of ``FLOOR_CANDIDATES`` on ``choice_runs`` and keep the
    one with the lower speed RMSE against the truth there (a tie or a NaN: the first).
    SUMO's files go to a folder under ``scratch``, removed at once."""
    t0 = time.perf_counter()
    runs = choice_runs(ctx, n_runs)
    det = pd.read_csv(ctx.truth_dir / "detectors.csv")
    truth = det[det["run"].isin(runs)].reset_index(drop=True)
    ref = truth_reference(ctx.truth_dir)
    interval_s = ctx.sc.deploy.compare_interval_s
    scores: dict[str, float] = {}
    by_run: dict[str, dict[int, float]] = {}
    deployed: list[str] = []
    scratch.mkdir(parents=True, exist_ok=True)
    for floor_on in FLOOR_CANDIDATES:
        folder = Path(tempfile.mkdtemp(prefix=f"floor_{floor_on}_", dir=scratch))
        try:
            res = run_method(ctx, dataclasses.replace(drive, floor_on=floor_on), folder, runs)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        scores[floor_on] = speed_rmse(truth, res.detectors, interval_s, ref.from_s)
        deployed.append(floor_on)
        det_run = res.detectors.groupby("run")
        by_run[floor_on] = {
            r: speed_rmse(truth[truth["run"] == r], det_run.get_group(r), interval_s, ref.from_s)
            for r in runs
        }
        if floor_on == FLOOR_CANDIDATES[0] and int(res.runs["floor_acted"].sum()) == 0:
            # "all" raised nothing, so every other floor (each raises a subset of what "all"
            # would at the same state) drives the same runs: a tie, not deployed again (the
            # paper's ring, where no driver slows below a fifth of the limit).
            for other in FLOOR_CANDIDATES[1:]:
                scores[other], by_run[other] = scores[floor_on], by_run[floor_on]
            break
    best = FLOOR_CANDIDATES[0]
    for floor_on in FLOOR_CANDIDATES[1:]:
        if scores[floor_on] < scores[best]:  # NaN compares False: the first stays
            best = floor_on
    return FloorChoice(best, scores, runs, time.perf_counter() - t0, by_run, tuple(deployed))


def resolve_floor(
    ctx: DeployContext, drive: Drive, scratch: Path
) -> tuple[Drive, dict[str, Any] | None]:
    """``drive`` with its floor chosen (``choose_floor``, ``deploy.safety_floor_runs`` runs)
    where ``deploy.safety_floor_on = "auto"`` asks for it, and the choice's record; else
    ``drive`` as it is and None."""
    if not needs_choice(ctx.sc, drive):
        return drive, None
    choice = choose_floor(ctx, drive, scratch, ctx.sc.deploy.safety_floor_runs)
    return dataclasses.replace(drive, floor_on=choice.chosen), choice.record()

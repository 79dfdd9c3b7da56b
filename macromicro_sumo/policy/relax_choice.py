"""The Krauss prior's relaxation time where the observed pairs leave it at its bound.

The free term min(a, (V - v) / T) closes a gap to the desired speed within T. The
recorded pairs decide T only where they show drivers far below their desired speed; on
ring_two_lane (recorded after the warm-up, steady traffic) none of 10,183 pairs shows free
acceleration, and the fit leaves T at its bound, 10 s (``evaluation.krauss_fit``): the
fleet, departing standing, then closes on its desired speed with a 10 s time constant and
the deployment's first minute ran 0.7-0.8 m/s slow (docs/deploy.md, "ring_two_lane's
cruise (stop 31)").

``choose_relax`` decides such a T from what the pairs do not show: the start. It drives
the demand of the runs Stage II trains on (``env.demand``'s demand episodes; never the
held-out runs) from SUMO's first step on, the population driven by the prior alone as a
deployment drives it, for each of ``RELAX_CANDIDATES_S``; runs the truth's induction
loops (``detectors.csv``'s E1) in SUMO beside it (``DemandCore.loop_table``: SUMO's own
counts and speeds); and keeps the T whose vehicle counts per interval are closest to the
truth's over the warm-up and the ``RELAX_SCORE_S`` after it (``choose_relax`` says why
counts). Stage II's own r_macro cannot decide it: its targets (psi) start after the
warm-up, when the start is over. Measured with SUMO's loops (stop 32): ring_two_lane and
netgen_corridor 10 -> 5 s; where every candidate's run collides (the prior alone drives
without a safety layer here: game/ramp, drawn nets 311 and 500-503) the fitted 10 s is
kept (``pick_relax``); highway_bremen's fit identifies T (0.59 s) and is left alone.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.demand_rollout import prior_step
from macromicro_sumo.policy.prior import RELAX_UPPER_S

# Candidates [s]: from near SUMO's Krauss (the step: a binds until the desired speed is
# within a x T) to the fit's bound (the neutral cruising the pairs fitted).
RELAX_CANDIDATES_S = (1.0, 2.0, 3.0, 5.0, 7.0, RELAX_UPPER_S)
# Scored over this span after the warm-up: the relaxation shapes how the population reaches
# its cruise (3 T: 30 s at the bound), and the first detector intervals hold it.
RELAX_SCORE_S = 120.0
# The fit's T counts as unidentified within this of its upper bound.
AT_BOUND_S = 0.01


def relax_unidentified(prior_params: Mapping[str, float]) -> bool:
    """True where the Krauss prior's relax_s [s] is at the fit's upper bound."""
    return float(prior_params["relax_s"]) >= RELAX_UPPER_S - AT_BOUND_S


@dataclass(frozen=True)
class LoopFit:
    """The simulated loops against the truth's over a candidate's runs."""

    count_rmse: float  # vehicles per interval, all loops together
    speed_rmse_mps: float  # their mean speeds, where both saw a vehicle
    passages: int
    collisions: int
    teleports: int


def loop_fit(
    sc: Any,
    prior_params: Mapping[str, float],
    core: DemandCore,
    span_s: float,
    family: str | None = None,
) -> LoopFit:
    """``LoopFit`` over every run of ``core`` from SUMO's first step to ``span_s`` after the
    warm-up, the population driven by the prior of ``prior_params`` alone (``family``:
    its model, ``policy.prior``'s when None), read by SUMO's own loops (the truth's E1
    detectors, ``DemandCore.loop_table``)."""
    agent = Agent(
        observation=sc.policy.observation,
        prior=family or sc.policy.prior,
        prior_params=prior_params,
    )
    dt, end_s = core.dt, sc.simulation.warmup_s + span_s
    det = core.truth.detectors
    counts, speeds, passages = [], [], 0
    c0, t0 = core.counts["collisions"], core.counts["teleports"]
    key = ["detector_id", "begin_s", "end_s"]
    for run in core.runs:
        truth = det[
            (det["run"] == int(run)) & (det["kind"] == "e1") & (det["end_s"] <= end_s + 1e-6)
        ]
        if truth.empty:
            continue
        core.reset(int(run), dt, loops=True)
        for _ in range(int(round(end_s / dt)) - 1):
            prior_step(agent, core)
        sim = core.loop_table()
        both = truth.merge(
            sim[key + ["n_veh", "speed_mps"]], on=key, how="left", suffixes=("", "_sim")
        )
        n_sim = both["n_veh_sim"].fillna(0.0)
        # Summed over the loops: which lane a vehicle passes on is SUMO's lane choice, noise
        # here (per loop, the candidates' count RMSEs did not order by T).
        per = both.assign(n_sim=n_sim).groupby("begin_s")[["n_sim", "n_veh"]].sum()
        counts.extend(per["n_sim"] - per["n_veh"])
        seen = (both["n_veh"] > 0) & (n_sim > 0)
        speeds.extend(both.loc[seen, "speed_mps_sim"] - both.loc[seen, "speed_mps"])
        passages += int(n_sim.sum())

    def rms(x: list[float]) -> float:
        return float(np.sqrt(np.mean(np.square(x)))) if x else float("nan")

    return LoopFit(
        rms(counts),
        rms(speeds),
        passages,
        core.counts["collisions"] - c0,
        core.counts["teleports"] - t0,
    )


def choose_relax(
    sc: Any,
    prior_params: Mapping[str, float],
    make_demand: Callable[[], DemandCore],
    candidates: tuple[float, ...] = RELAX_CANDIDATES_S,
    span_s: float = RELAX_SCORE_S,
) -> tuple[float, dict[str, Any]]:
    """(relax_s [s], what the manifest records): the candidate (at least the step) whose
    loops' counts are closest to the truth's (``LoopFit.count_rmse``), among those without
    a collision; the fitted T where every one collided (``pick_relax``); equal ones keep
    the larger T (the fit's side): a slower start passes fewer vehicles. Counts, not speeds, though SUMO's loops read both exactly:
    a loop's speed is also which lane SUMO's lane changing put the vehicles on
    (ring_two_lane's per-loop speeds keep 3 s, pooled over each station's lanes 5 s as the
    counts), and where a deployment gives each driver its own desired speed
    (``policy.driver_speed``) the prior alone here gives them one, runs 1-2 m/s fast on
    netgen_corridor and game/ramp, and the speeds reward the slowest start (10 s)."""
    dt = sc.simulation.step_length_s
    core = make_demand()
    rows: list[tuple[float, LoopFit]] = []
    try:
        for t in sorted({max(float(c), dt) for c in candidates}, reverse=True):
            fit = loop_fit(sc, {**prior_params, "relax_s": t}, core, span_s, family="krauss")
            rows.append((t, fit))
        runs = [int(r) for r in core.runs]
    finally:
        core.close()
    fitted_s = float(prior_params["relax_s"])
    chosen_s = pick_relax(rows, fitted_s)
    record = {
        "fitted_s": fitted_s,
        "chosen_s": chosen_s,
        "runs": runs,
        "span_s": span_s,
        "candidates": {f"{t:g}": asdict(f) for t, f in rows},
    }
    if chosen_s == fitted_s and not any(_scored(f) for _, f in rows):
        record["kept_fitted"] = "every candidate's run collided: no count is a measurement"
    return chosen_s, record


def _scored(fit: LoopFit) -> bool:
    return fit.collisions == 0 and bool(np.isfinite(fit.count_rmse))


def pick_relax(rows: list[tuple[float, LoopFit]], fitted_s: float) -> float:
    """The candidate T of ``rows`` (T, its ``LoopFit``) whose counts are closest to the
    truth's among those whose runs did not collide (equals: the first, the larger T); the
    fitted ``fitted_s`` where every run collided. The prior alone drives without a safety
    layer here, and a run of crashes says nothing of how a population starts: on drawn net
    311 every candidate collided 606-906 times, the counts (RMSE 71-86 vehicles per interval
    against 4-10 on ring_two_lane and netgen_corridor) picked 7 s, and the policy trained on
    it deployed at 4.74 m/s speed RMSE where the fitted 10 s gave 2.47 (docs/deploy.md,
    "The relaxation choice on crashed runs (stop 32)")."""
    safe = [r for r in rows if _scored(r[1])]
    if not safe:
        return fitted_s
    return min(safe, key=lambda r: r[1].count_rmse)[0]  # min keeps the first of equals

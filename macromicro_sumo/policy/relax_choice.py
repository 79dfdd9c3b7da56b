"""The Krauss prior's relaxation time where the observed pairs leave it at its bound.

The free term min(a, (V - v) / T) closes a gap to the desired speed within T. The
recorded pairs decide T only where they show drivers far below their desired speed; on
ring_two_lane (recorded after the warm-up, steady traffic) none of 10,183 pairs shows free
acceleration, and the fit leaves T at its bound, 10 s (``evaluation.krauss_fit``): the
fleet, departing standing, then closes on its desired speed with a 10 s time constant and
the deployment's first minute ran 0.7-0.8 m/s slow (docs/deploy-log.md, "ring_two_lane's
cruise (stop 31)").

``choose_relax`` decides such a T from what the pairs do not show: the start. Each of
``RELAX_CANDIDATES_S`` is scored by the project's one prior-alone scorer, the one
``policy.prior = "auto"`` ranks the families with (``policy.prior_choice.PriorDeploy``,
``deploy.prior_score.deploy_prior``: the deployment itself, its safety layer, floor and
drivers' desired speeds, on the first ``deploy.safety_floor_runs`` training runs from
SUMO's first step, warm-up included), and the one with the lowest speed RMSE against the
truth's detectors there is kept. Stage II's own r_macro cannot decide it: its targets
(psi) start after the warm-up, when the start is over. Nor can the demand env Stage II
trains on: it drives without the safety layer, and on congested networks every candidate's
run collided there (drawn net 311: 606-906 times; deployed, none did; docs/deploy-log.md,
"One prior-alone scorer (stop 33)").
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from macromicro_sumo.policy.prior import RELAX_UPPER_S

# Candidates [s]: from near SUMO's Krauss (the step: a binds until the desired speed is
# within a x T) to the fit's bound (the neutral cruising the pairs fitted).
RELAX_CANDIDATES_S = (1.0, 2.0, 3.0, 5.0, 7.0, RELAX_UPPER_S)
# The fit's T counts as unidentified within this of its upper bound.
AT_BOUND_S = 0.01

# A prior's parameters deployed alone: {"speed_rmse_mps": ..., "collisions": ..., ...}
# (``deploy.prior_score.deploy_prior``'s figures; a policy module may not import the
# deployment: the policy stage passes it in, ``policy.prior_choice.PriorDeploy``).
ParamsScore = Callable[[Mapping[str, float]], dict[str, Any]]


def relax_unidentified(prior_params: Mapping[str, float]) -> bool:
    """True where the Krauss prior's relax_s [s] is at the fit's upper bound."""
    return float(prior_params["relax_s"]) >= RELAX_UPPER_S - AT_BOUND_S


def rank_key(score: Mapping[str, Any]) -> tuple[bool, float]:
    """Lower is better: a collision-free deployment first, then the speed RMSE (NaN last)."""
    rmse = float(score["speed_rmse_mps"])
    return score["collisions"] > 0, rmse if np.isfinite(rmse) else float("inf")


def choose_relax(
    prior_params: Mapping[str, float],
    score: ParamsScore,
    step_s: float,
    candidates: tuple[float, ...] = RELAX_CANDIDATES_S,
) -> tuple[float, dict[str, Any]]:
    """(relax_s [s], what the manifest records): of ``candidates`` (at least the step
    ``step_s``), the one whose prior alone (``prior_params`` with that relax_s), deployed
    by ``score``, has the lowest speed RMSE against the truth's detectors, a collision-free
    one before any other (``rank_key``; equals keep the larger T, the fit's side). The
    record holds every candidate's figures, the chosen one's for a caller that would deploy
    it again (``policy.prior_choice.choose_prior``)."""
    t0 = time.perf_counter()
    scores: dict[float, dict[str, Any]] = {}
    for t in sorted({max(float(c), step_s) for c in candidates}, reverse=True):
        scores[t] = score({**prior_params, "relax_s": t})
    chosen_s = min(scores, key=lambda t: rank_key(scores[t]))  # min keeps the first of equals
    record = {
        "fitted_s": float(prior_params["relax_s"]),
        "chosen_s": chosen_s,
        "score": "speed_rmse_mps of the prior alone deployed on training runs",
        "wall_s": round(time.perf_counter() - t0, 1),
        "candidates": {f"{t:g}": s for t, s in scores.items()},
    }
    return chosen_s, record

"""``policy.prior = "auto"``: the prior's model family chosen on the training runs.

Which family a section's residual policy should rest on is not a property of the fit: on
drawn net 300 the IDM prior's trained policy deployed at 4.83-6.42 m/s speed RMSE and the
Krauss prior's at 6.86-7.34, on drawn net 311 Krauss at 2.82 and IDM at 3.41 (docs/deploy.md,
"A policy that knows its vehicle's length (stop 31)"), while each example file picked its
family by hand. ``choose_prior`` fits every family of ``PRIOR_FAMILIES`` to the same pairs
(``fit_family``: as the policy stage fits one, the Krauss form with its relaxation choice,
``policy.relax_choice``), deploys each prior alone (the residual at 0) on training runs
(never the held-out runs; ``PriorScore``, ``deploy.prior_score``), and keeps the family
whose speed RMSE against the truth's detectors there is lowest.

The choice is made once, by the policy stage; the checkpoint records the family and every
later reader takes it from there (``policy.checkpoint.trained_prior``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.relax_choice import choose_relax, relax_unidentified

# Fits ``policy.prior``'s model to the observed pairs of the given runs of a ground truth:
# (the agent's prior parameters, what the manifest records of the fit, the pairs (obs,
# accel) it was fitted on, which the residual's likelihood uses: ``policy.residual``). The
# fit is the evaluation's (a policy module may not import it): the pipeline passes it in.
PriorFit = Callable[
    [Any, Any, np.ndarray],
    tuple[dict[str, float], dict[str, Any], tuple[np.ndarray, np.ndarray]],
]
FittedPrior = tuple[dict[str, float], dict[str, Any], tuple[np.ndarray, np.ndarray]]

# A prior alone (an ``Agent`` whose residual bound is 0) deployed on training runs of the
# ground truth in the given folder: {"speed_rmse_mps": ..., "collisions": ..., ...}
# (``deploy.prior_score.deploy_prior``; a policy module may not import the deployment:
# the pipeline passes it in).
PriorScore = Callable[[Any, Path, Agent], dict[str, Any]]

# The candidates, in the order a tie keeps them.
PRIOR_FAMILIES = ("krauss", "idm", "gipps")


def with_prior(sc: Any, family: str) -> Any:
    """``sc`` with ``policy.prior = family``: what every stage after the choice reads."""
    return dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, prior=family))


def fit_family(
    sc: Any,
    truth: Any,
    runs: np.ndarray,
    fit_prior: PriorFit,
    make_demand: Callable[[], DemandCore] | None,
) -> FittedPrior:
    """``sc.policy.prior``'s model fitted to ``runs``' observed pairs (``fit_prior``); a
    Krauss relaxation time the pairs leave at its bound chosen on the training runs'
    demand, warm-up included, by the prior alone (``policy.relax_choice``)."""
    prior, extra, pairs = fit_prior(sc, truth, runs)
    if sc.policy.prior == "krauss" and relax_unidentified(prior) and make_demand is not None:
        prior["relax_s"], extra["prior"]["relax_choice"] = choose_relax(sc, prior, make_demand)
        extra["prior"]["relax_s"] = prior["relax_s"]
    return prior, extra, pairs


def rank_key(score: dict[str, Any]) -> tuple[bool, float]:
    """Lower is better: a collision-free deployment first, then the speed RMSE (NaN last)."""
    rmse = float(score["speed_rmse_mps"])
    return score["collisions"] > 0, rmse if np.isfinite(rmse) else float("inf")


def choose_prior(
    sc: Any,
    truth: Any,
    runs: np.ndarray,
    fit_prior: PriorFit,
    make_demand: Callable[[], DemandCore] | None,
    score_prior: PriorScore,
    data: Path,
    driver_speed: np.ndarray | None = None,
    families: tuple[str, ...] = PRIOR_FAMILIES,
    progress: bool = False,
) -> tuple[str, FittedPrior]:
    """(the family kept, its ``fit_family``): each of ``families`` fitted to ``runs``' pairs
    and deployed alone by ``score_prior`` on training runs of the truth in ``data``, its
    drivers' speeds ``driver_speed`` (``policy.driver_speed``) as the trained policy's
    will be; the one with the lowest speed RMSE there kept, a collision-free one before any
    other (``rank_key``; equals: the first of ``families``). Every candidate's fit and
    deployment figures and the choice go into the manifest record
    (``extra["prior"]["choice"]``). The deployment's speed RMSE, not the fit's: the fit
    ranks the families by the observed pairs (net 300: IDM 0.90, Krauss 1.25 m/s^2),
    not by what the population does with them, and the report judges the latter."""
    t0 = time.perf_counter()
    fits: dict[str, FittedPrior] = {}
    scores: dict[str, dict[str, Any]] = {}
    for family in families:
        t1 = time.perf_counter()
        one = with_prior(sc, family)
        fits[family] = fit_family(one, truth, runs, fit_prior, make_demand)
        agent = Agent(
            observation=sc.policy.observation,
            prior=family,
            prior_params=fits[family][0],
            residual_bound_mps2=0.0,  # the prior alone
            driver_speed=driver_speed,
        )
        scores[family] = score_prior(one, data, agent)
        if progress:
            print(
                f"[prior auto] {family}: deployed alone, speed RMSE "
                f"{scores[family]['speed_rmse_mps']:.3f} m/s, collisions "
                f"{scores[family]['collisions']} ({time.perf_counter() - t1:.0f} s)"
            )
    chosen = min(families, key=lambda f: rank_key(scores[f]))  # min keeps the first of equals
    record = {
        "chosen": chosen,
        "score": "speed_rmse_mps of the prior alone deployed on training runs",
        "wall_s": round(time.perf_counter() - t0, 1),
        "candidates": {
            f: {
                "deployed": scores[f],
                "params": dict(fits[f][0]),
                "fit_rmse_mps2": fits[f][1]["prior"].get("fit_rmse_mps2"),
                "relax_choice_s": fits[f][1]["prior"].get("relax_choice", {}).get("chosen_s"),
            }
            for f in families
        },
    }
    if progress:
        print(f"[prior auto] kept {chosen} ({record['wall_s']:.0f} s)")
    prior, extra, pairs = fits[chosen]
    extra["prior"]["choice"] = record
    return chosen, (prior, extra, pairs)

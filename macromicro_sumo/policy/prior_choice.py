"""``policy.prior = "auto"``: the prior's model family chosen on the training runs.

Which family a section's residual policy should rest on is not a property of the fit: on
drawn net 300 the IDM prior's trained policy deployed at 4.83-6.42 m/s speed RMSE and the
Krauss prior's at 6.86-7.34, on drawn net 311 Krauss at 2.82 and IDM at 3.41 (docs/deploy-log.md,
"A policy that knows its vehicle's length (stop 31)"), while each example file picked its
family by hand. ``choose_prior`` fits every family of ``PRIOR_FAMILIES`` to the same pairs
(``fit_family``: as the policy stage fits one, the Krauss form with its relaxation choice,
``policy.relax_choice``), deploys each prior alone (the residual at 0) on training runs
(never the held-out runs; ``PriorDeploy``, ``deploy.prior_score``), and keeps the family
whose speed RMSE against the truth's detectors there is lowest. ``PriorDeploy`` is the
project's one prior-alone scorer: the Krauss relaxation choice ranks its candidates with it
too, and the family choice takes the chosen relaxation's figures from there.

The choice is made once, by the policy stage; the checkpoint records the family and every
later reader takes it from there (``policy.checkpoint.trained_prior``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.relax_choice import choose_relax, rank_key, relax_unidentified

# The residual's likelihood pairs (``policy.residual``): observations (N, D), accelerations
# (N,), and each pair's driver's own tau [s] (N,) where the Krauss fit gives the drivers'
# taus (``policy.driver_follow``), else None (the prior's one tau).
LikelihoodPairs = tuple[np.ndarray, np.ndarray, np.ndarray | None]
# Fits ``policy.prior``'s model to the observed pairs of the given runs of a ground truth:
# (the agent's prior parameters, what the manifest records of the fit, the pairs it was
# fitted on, ``LikelihoodPairs``). The fit is the evaluation's (a policy module may not
# import it): the pipeline passes it in.
PriorFit = Callable[
    [Any, Any, np.ndarray],
    tuple[dict[str, float], dict[str, Any], LikelihoodPairs],
]
FittedPrior = tuple[dict[str, float], dict[str, Any], LikelihoodPairs]

# A prior alone (an ``Agent`` whose residual bound is 0) deployed on training runs of the
# ground truth in the given folder: {"speed_rmse_mps": ..., "collisions": ..., ...}
# (``deploy.prior_score.deploy_prior``; a policy module may not import the deployment:
# the pipeline passes it in).
PriorScore = Callable[[Any, Path, Agent], dict[str, Any]]

# The candidates, in the order a tie keeps them.
PRIOR_FAMILIES = ("krauss", "idm", "gipps")


@dataclass(frozen=True)
class PriorDeploy:
    """The project's one prior-alone scorer, as the policy stage has it: the deployment
    (``score``), the ground truth's folder, the drivers' desired-speed quantiles the trained
    policy's will have (``policy.driver_speed``), and whether to print. Called with a
    scenario (its ``policy.prior`` the family) and the prior's parameters."""

    score: PriorScore
    data: Path
    driver_speed: np.ndarray | None = None
    progress: bool = False
    # The drivers' tau quantiles (``policy.driver_follow``'s "auto" deploys with them).
    driver_tau: np.ndarray | None = None

    def __call__(self, sc: Any, params: Mapping[str, float]) -> dict[str, Any]:
        agent = Agent(
            observation=sc.policy.observation,
            prior=sc.policy.prior,
            prior_params=params,
            residual_bound_mps2=0.0,  # the prior alone
            driver_speed=self.driver_speed,
            driver_tau=self.driver_tau,
        )
        return self.score(sc, self.data, agent)


def with_prior(sc: Any, family: str) -> Any:
    """``sc`` with ``policy.prior = family``: what every stage after the choice reads."""
    return dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, prior=family))


def fit_family(
    sc: Any,
    truth: Any,
    runs: np.ndarray,
    fit_prior: PriorFit,
    deploy: PriorDeploy | None,
) -> FittedPrior:
    """``sc.policy.prior``'s model fitted to ``runs``' observed pairs (``fit_prior``); a
    Krauss relaxation time the pairs leave at its bound chosen by ``deploy``, the prior
    alone deployed on training runs with each candidate (``policy.relax_choice``; without
    ``deploy`` it stays at the bound)."""
    prior, extra, pairs = fit_prior(sc, truth, runs)
    if sc.policy.prior == "krauss" and relax_unidentified(prior) and deploy is not None:
        t0 = time.perf_counter()
        prior["relax_s"], record = choose_relax(
            prior, lambda p: deploy(sc, p), sc.simulation.step_length_s
        )
        extra["prior"]["relax_choice"] = record
        extra["prior"]["relax_s"] = prior["relax_s"]
        if deploy.progress:
            print(
                f"[prior krauss] relax_s {prior['relax_s']:g} s kept of "
                f"{len(record['candidates'])} deployed alone ({time.perf_counter() - t0:.0f} s)"
            )
    return prior, extra, pairs


def choose_prior(
    sc: Any,
    truth: Any,
    runs: np.ndarray,
    fit_prior: PriorFit,
    deploy: PriorDeploy,
    families: tuple[str, ...] = PRIOR_FAMILIES,
) -> tuple[str, FittedPrior]:
    """(the family kept, its ``fit_family``): each of ``families`` fitted to ``runs``' pairs
    and deployed alone by ``deploy`` on training runs, its drivers' speeds as the trained
    policy's will be; the one with the lowest speed RMSE there kept, a collision-free one
    before any other (``rank_key``; equals: the first of ``families``). A Krauss prior whose
    relaxation was chosen was deployed with it there: that figure is taken, not deployed
    again. Every candidate's fit and deployment figures and the choice go into the manifest
    record (``extra["prior"]["choice"]``). The deployment's speed RMSE, not the fit's: the
    fit ranks the families by the observed pairs (net 300: IDM 0.90, Krauss 1.25 m/s^2),
    not by what the population does with them, and the report judges the latter."""
    t0 = time.perf_counter()
    fits: dict[str, FittedPrior] = {}
    scores: dict[str, dict[str, Any]] = {}
    for family in families:
        t1 = time.perf_counter()
        one = with_prior(sc, family)
        fits[family] = fit_family(one, truth, runs, fit_prior, deploy)
        relax = fits[family][1]["prior"].get("relax_choice")
        if relax is not None:  # the chosen relaxation's deployment: the same configuration
            scores[family] = relax["candidates"][f"{relax['chosen_s']:g}"]
        else:
            scores[family] = deploy(one, fits[family][0])
        if deploy.progress:
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
    if deploy.progress:
        print(f"[prior auto] kept {chosen} ({record['wall_s']:.0f} s)")
    prior, extra, pairs = fits[chosen]
    extra["prior"]["choice"] = record
    return chosen, (prior, extra, pairs)

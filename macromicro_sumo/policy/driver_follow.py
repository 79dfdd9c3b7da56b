"""Stage II's side of ``policy.driver_follow``: the drivers' tau quantiles the policy
trains and deploys with (``driver_tau_quantiles``) and the training inputs that carry each
row's tau (``follow_inputs``).

* The quantiles: each observed driver's own tau on the training runs
  (``evaluation.driver_follow.driver_taus``, the prior's other parameters at the fitted
  ones), which the Krauss prior's fit records (``driver_tau_record``'s ``levels_s``: the
  pipeline's fit, passed in as ``policy.prior_choice.PriorFit``); None (the prior's one
  tau) with ``driver_follow = "none"``, a prior other than Krauss, or fewer than
  ``evaluation.driver_follow.MIN_DRIVER_TAUS`` (30) drivers with a tau.
* The snapshot episodes: each bank slot draws its tau from them (``slot_tau_levels``, a
  generator seeded by the scenario's seed), the rollouts append it
  (``policy.rollout.own_taus``).
* ``"auto"`` (``follow_choice``): the prior alone deployed on training runs with its one
  tau and with the draws (``policy.prior_choice.PriorDeploy``, the project's one
  prior-alone scorer, as ``policy.relax_choice`` ranks its candidates); the draws are
  kept where their speed RMSE is lower (a tie keeps the one tau). The manifest records
  both figures and the choice.
* The residual's likelihood pairs (the observed drivers' recorded pairs) carry each pair's
  driver's own tau (``evaluation.driver_follow.pair_taus``: its fitted one, else the
  deployment's draw for that driver), so the likelihood fits every observed driver with
  the headway it keeps; pairs without them (a fit from before, or none kept) carry the
  prior's one tau, the one the prior was fitted with.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from macromicro_sumo.env.driver_tau import (
    pooled_quantiles,
    slot_tau_levels,
    taus_at,
    vtype_table,
    with_tau,
)
from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.errors import UserError
from macromicro_sumo.policy.prior_choice import LikelihoodPairs, PriorDeploy
from macromicro_sumo.policy.relax_choice import rank_key


def driver_tau_quantiles(sc, record: Mapping[str, Any] | None) -> tuple[np.ndarray | None, int]:
    """The observed drivers' tau quantiles where ``policy.driver_follow`` draws them, from
    the Krauss prior's fit record (``record``: its ``driver_taus``,
    ``evaluation.driver_follow.driver_tau_record``, which the pipeline's fit makes), and how
    many drivers gave a tau; None: the one tau (not asked, not a Krauss prior, or too few
    drivers with a tau)."""
    if sc.policy.driver_follow == "none" or not record:
        return None, 0
    levels = record.get("levels_s")
    q = None if levels is None else np.asarray(levels, dtype=float)
    setting = sc.policy.driver_follow
    by = record.get(setting) if setting in ("by_vtype", "by_vtype_gap") else None
    if q is not None and by:  # a table: the pooled row, then each vType's own
        q = vtype_table(q, {name: r["levels_s"] for name, r in by.items()})
    return q, int(record.get("drivers", 0))


def follow_choice(
    sc,
    fitted: Mapping[str, Any],
    prior: Mapping[str, float] | None,
    deploy: PriorDeploy | None,
) -> tuple[np.ndarray | None, dict[str, Any] | None]:
    """``policy.driver_follow``'s tau quantiles for the policy (None: the one tau) and what
    the policy manifest records (None with "none"), from the prior's fit record
    (``fitted``: the policy manifest's ``prior``): "drawn" takes the drivers' quantiles
    where there are enough; "auto" keeps them where the prior alone deployed with them
    (``deploy``) beats its one tau on the training runs (``rank_key``)."""
    setting = sc.policy.driver_follow
    if setting == "none":
        return None, None
    t0 = time.perf_counter()
    q, drivers = driver_tau_quantiles(sc, fitted.get("driver_taus"))
    record: dict[str, Any] = {"setting": setting, "drivers_with_tau": drivers}
    pooled = None if q is None else pooled_quantiles(q)
    record["quantiles_s"] = None if q is None else [round(float(x), 4) for x in pooled]
    if q is not None and q.ndim == 2:  # by_vtype: the vTypes with their own, and medians
        by = fitted.get("driver_taus", {}).get(setting, {})
        record["by_vtype"] = {n: {k: r[k] for k in ("drivers", "median_s")} for n, r in by.items()}
    if q is not None and setting == "auto":
        if deploy is None:
            raise UserError(
                f"{sc.source}: policy.driver_follow = 'auto' is chosen by a section's policy "
                "stage with its prior-alone deployment; accepted here: 'none' or 'drawn'"
            )
        one = deploy(sc, prior)
        drawn = dataclasses.replace(deploy, driver_tau=q)(sc, prior)
        record["candidates"] = {"none": one, "drawn": drawn}
        q = q if rank_key(drawn) < rank_key(one) else None
    record["chosen"] = "none" if q is None else setting if q.ndim == 2 else "drawn"
    record["wall_s"] = round(time.perf_counter() - t0, 1)
    return q, record


def follow_inputs(
    bank: SectionBank,
    pairs: LikelihoodPairs | tuple[np.ndarray, np.ndarray] | None,
    prior: Mapping[str, float] | None,
    quantiles: np.ndarray | None,
    seed: int,
) -> tuple[SectionBank, LikelihoodPairs | tuple[np.ndarray, np.ndarray] | None]:
    """The bank with each slot's tau drawn from ``quantiles`` and the likelihood ``pairs``
    with each pair's driver's own tau (their third item, ``LikelihoodPairs``) as their
    trailing column, or the prior's one tau where they have none; both as they are without
    ``quantiles``."""
    if quantiles is None:
        return bank, pairs
    # float32 as the agent's buffer: a slot's tau is the one the deployment would draw;
    # by_vtype's slots (no vType) draw from its pooled row.
    q = pooled_quantiles(np.asarray(quantiles, dtype=np.float32).astype(float))
    taus = taus_at(q, slot_tau_levels(seed, bank.valid.shape))
    bank = SectionBank(**{**bank.__dict__, "driver_tau": taus})
    own = pairs[2] if pairs is not None and len(pairs) > 2 else None
    if pairs is not None and own is not None:
        obs = np.asarray(pairs[0])
        pairs = (with_tau(obs, np.asarray(own, dtype=obs.dtype)), pairs[1], own)
    elif pairs is not None and prior is not None:
        pairs = (with_tau(np.asarray(pairs[0]), float(prior["tau_s"])), pairs[1], None)
    return bank, pairs

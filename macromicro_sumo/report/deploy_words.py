"""Sentences of the deployment section read from deploy_summary.csv alone, beside the
verdicts of ``report.deploy``: how often the safety layer acted, and the oracle where it
reproduces the ground truth (a check of the deployment, not a bar for the policy)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from macromicro_sumo.deploy.safety import FLOOR_SHARE


def acted_lines(summary: pd.DataFrame) -> list[str]:
    """Per method whose speed commands went through the safety layer: how many it lowered
    (to the safe speed behind the leader) and raised (to its floor), of the driven
    vehicle-steps (``deploy.compare.ACTED_SHARES``)."""

    def of(n: float, total: float) -> str:
        return f"{n:,.0f} ({100 * n / total:.1f}%)" if np.isfinite(n) else "n/a (not recorded)"

    lines = []
    for _, r in summary.iterrows():
        driven = float(r.get("vehicle_steps_driven", np.nan))
        lowered, raised = (float(r.get(c, np.nan)) for c in ("safety_acted", "floor_acted"))
        share = float(r.get("safety_floor_share", np.nan))  # deploy.safety_floor_share
        share = share if np.isfinite(share) else FLOOR_SHARE
        if not (driven > 0 and (lowered > 0 or raised > 0)):
            continue
        lines.append(
            f"- `{r['method']}`: of {driven:,.0f} driven vehicle-steps, the safety layer "
            f"lowered the command to the safe speed behind the leader in {of(lowered, driven)} "
            f"and raised it to its floor ({share:.0%} of the lane's limit) in "
            f"{of(raised, driven)}."
        )
    return lines


def reproduces_truth(summary: pd.DataFrame, method: str) -> bool:
    """Whether ``method``'s detectors are the reference's to the digit: every
    station-interval within both targets, no speed or density error (the oracle on a
    simulated truth: the same models, demand and seeds)."""
    r = summary.set_index("method").loc[method]
    shares = (r["share_geh_below_5"], r["share_speed_within_5pct"])
    errors = (r["speed_rmse_mps"], r["density_rmse_vpkm"])
    return all(s == 1.0 for s in shares) and all(e == 0.0 for e in errors)


def oracle_check(summary: pd.DataFrame, policy: str, floors: Sequence[str]) -> list[str]:
    """The oracle where it reproduces the ground truth (``reproduces_truth``), in words: a
    check of the deployment, not a bar (the policy would trail it on every figure by its
    own error); its emergency brakings are the ground truth's own. ``floors``: the methods
    that say what a model of the population reaches, named where deployed."""
    s = summary.set_index("method")
    line = (
        "- The oracle (`oracle`: every vehicle on its own model, the ground truth's seeds) "
        "reproduces the ground truth's detectors exactly: a check of the deployment, not a "
        "bar for a model of the population"
    )
    named = [f"`{name}`" for name in floors if name in s.index]
    if named:
        line += f" (what one reaches: {' and '.join(named)}, above)"
    braking = float(s.loc["oracle"].get("emergency_brakings", np.nan))
    mine = float(s.loc[policy].get("emergency_brakings", np.nan))
    if np.isfinite(braking) and np.isfinite(mine):
        line += (
            f". Its {braking:,.0f} emergency brakings are the ground truth's own (the "
            f"policy's: {mine:,.0f})"
        )
    return [line + "."]

"""Stage II: policy checkpoints (``policy.pt``, ``policy_<objective>_checkpoint.pt``).

A checkpoint carries a format tag and the ``signature`` of the scenario it was trained
for; one that is corrupt, not a policy checkpoint or trained for another scenario is a
one-line UserError, and so is one trained with another ``policy.prior`` (recorded as
"prior"; the prior's parameters and the residual's bound are in the state_dict). With
``policy.prior = "auto"`` the family is the one the policy stage chose and recorded:
``trained_prior`` is where every reader gets it.
``load_policy`` gives the trained agent; ``resumable_checkpoint`` the
training state to continue from (the one resume rule of every stage).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from macromicro_sumo.env.driver_speed_ratios import quantile_median
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import check_beside
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.prior import PRIORS
from macromicro_sumo.road.physics import OBSERVATION_FEATURES
from macromicro_sumo.scenario.section import SectionScenario

CHECKPOINT_FORMAT = "macromicro-policy"


def signature(sc: SectionScenario) -> dict[str, Any]:
    """What a policy checkpoint must agree on with the scenario that loads it."""
    return {
        "network.kind": "sumo",
        "section.edges": ",".join(sc.section.edges),
        "section.closed": sc.section.closed,
        "bounds.accel_mps2": list(sc.bounds.accel_mps2),
        "simulation.step_length_s": sc.simulation.step_length_s,
        "policy.observation": ",".join(OBSERVATION_FEATURES[sc.policy.observation]),
    }


def read_checkpoint(path: Path) -> dict[str, Any]:
    """A policy checkpoint's payload, whatever scenario it was trained for."""
    try:
        # weights_only: a checkpoint is data; a crafted pickle must never run code here.
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise UserError(
            f"{path}: corrupt or truncated policy checkpoint ({type(exc).__name__})"
        ) from None
    fmt = payload.get("format") if isinstance(payload, dict) else None
    if fmt != CHECKPOINT_FORMAT:
        what = f"a {fmt!r} file" if isinstance(fmt, str) else "no format tag"
        raise UserError(
            f"{path}: not a policy checkpoint ({what}); pass the policy.pt of train-policy"
        )
    return payload


def load_checkpoint(path: Path, sc: SectionScenario) -> dict[str, Any]:
    payload = read_checkpoint(path)
    want = signature(sc)
    for key, have in payload["signature"].items():
        if want.get(key) != have:
            raise UserError(
                f"{path}: policy was trained for {key} = {have}, scenario {sc.source} has {want.get(key)}"
            )
    trained_prior(payload, sc, path)
    have = payload.get("driver_speed", "none")  # checkpoints from before it: none
    want_speed = getattr(sc.policy, "driver_speed", "none")
    if have != want_speed:
        raise UserError(
            f"{path}: policy was trained with policy.driver_speed = {have!r}, scenario "
            f"{sc.source} has {want_speed!r}"
        )
    return payload


def trained_prior(payload: dict[str, Any], sc: SectionScenario, path: Path | str) -> str:
    """The prior family a policy checkpoint drives with: the one it was trained with
    (``"prior"``; "none" in checkpoints from before ``policy.prior``), which must be the
    scenario's ``policy.prior``, or one of the families ``"auto"`` chooses from where the
    scenario says "auto" (the policy stage resolved it once: ``policy.prior_choice``)."""
    # Not in the signature, so that checkpoints from before policy.prior still load: the
    # policy's mean is another function with and without a prior.
    have = payload.get("prior", "none")
    want = sc.policy.prior
    if have == want or (want == "auto" and have in PRIORS and have != "none"):
        return have
    raise UserError(
        f"{path}: policy was trained with policy.prior = {have!r}, scenario {sc.source} has "
        f"{want!r}"
    )


def resumable_checkpoint(
    path: Path, sc: SectionScenario, run_key: str, resume: bool | str
) -> dict[str, Any] | None:
    """The checkpoint to continue from, if any.

    ``resume`` True: the checkpoint must be of this very run (same scenario, ground truth,
    generator and objective: ``run_key``) or it is an error; "auto": such a checkpoint is
    used and any other ignored, whatever scenario it was trained for (the pipeline after an
    input changed: training starts afresh and replaces it); False: none. A file that is not
    a policy checkpoint is an error either way.
    """
    if not resume or not path.is_file():
        return None
    if resume == "auto" and read_checkpoint(path).get("run_key") != run_key:
        return None
    ck = load_checkpoint(path, sc)
    if ck.get("run_key") != run_key:
        raise UserError(
            f"{path}: checkpoint belongs to another run (scenario, ground truth, generator or objective "
            "differ); start without --resume or use another --out"
        )
    return ck


def policy_file(objective: str, kind: str = "pt") -> str:
    """What a policy stage of ``objective`` names its files: ``policy.pt`` for the paper's
    objective, ``policy_micro_only.pt`` for an ablation; ``kind`` ``manifest`` or
    ``train_log`` for the stage's other files."""
    suffix = "" if objective == "mix" else f"_{objective}"
    return {
        "pt": f"policy{suffix}.pt",
        "manifest": f"policy_manifest{suffix}.json",
        "train_log": f"policy_train_log{suffix}.csv",
    }[kind]


def load_policy(path: Path | str, sc: SectionScenario, speed_level: str = "fit") -> Agent:
    """The trained policy at ``path`` for ``sc``; ``speed_level``: ``deploy.speed_level``,
    passed by the deployment only (Stage II's evaluation judges the policy as trained)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: policy checkpoint not found (run `macromicro train-policy`)")
    # policy.pt -> policy_manifest.json, policy_micro_only.pt -> policy_manifest_micro_only.json
    objective = path.stem.removeprefix("policy").removeprefix("_") or "mix"
    check_beside(path, policy_file(objective, "manifest"))
    payload = load_checkpoint(path, sc)
    agent = Agent(
        payload["hidden_size"],
        observation=sc.policy.observation,
        prior=trained_prior(payload, sc, path),
        driver_speed=payload["state_dict"].get("driver_speed"),
    )
    agent.load_state_dict(payload["state_dict"])
    agent.eval()
    return with_speed_level(agent, speed_level)


def with_speed_level(agent: Agent, level: str) -> Agent:
    """``agent`` with ``deploy.speed_level`` applied, in place: "fit" as trained; "tops", the
    Krauss prior's speed factor (the median driver's desired speed over the limit) set to the
    median of the drivers' ratio estimate (its ``driver_speed`` buffer, the observed drivers'
    top v / limit, ``env.driver_speed_ratios``), so that each deployed driver's desired speed is
    its drawn top speed rather than the fit's level below it. An agent without the Krauss prior
    or the drivers' quantiles is left as it is.

    Why: the fit reads the level from every pair of the free drivers, scaled by their ratio
    over the median, so it takes in what keeps a SUMO driver below its top: Krauss' dawdling
    and the acceleration phases (drawn 522: speed factor 0.984 = 0.969 x the median 1.016;
    the truth's free drivers cruise at 0.974-0.986 of their tops; highway_bremen 0.993 x).
    A deployed driver does not dawdle, and on one-lane edges a platoon runs at its leader's
    desired speed: on drawn 522 the policy ran 0.8-1.5 m/s slow downstream of the drop on
    every PPO seed (stop 49, hM49). Measured (all 4 runs, stop 50, hM50): 522 over 11 PPO
    seeds, downstream bias -0.93 -> -0.20 m/s on every seed, speed RMSE 2.605 -> 2.553 (noise);
    it loses on highway_bremen (0.914 -> 1.423), netgen_corridor (0.460 -> 0.627), 549, 565
    and 1702, wins on 1046 (1.002 -> 0.884) and 1803: opt-in, where the fit's level is the
    truth's cruising one it is too fast."""
    if level == "fit" or agent.prior != "krauss" or agent.driver_speed is None:
        return agent
    quantiles = agent.driver_speed.detach().double().numpy()
    with torch.no_grad():
        agent.krauss_prior[0] = quantile_median(quantiles)
    return agent

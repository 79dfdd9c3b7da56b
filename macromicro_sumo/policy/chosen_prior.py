"""The prior's choices made once per run, in one file every learned method's stage reads.

``policy.prior = "auto"`` (the family, ``policy.prior_choice``) and the Krauss prior's
relaxation where the observed pairs leave it at its bound (``policy.relax_choice``) deploy
candidate priors alone on training runs: minutes. The paper's policy and its two ablations
(micro_only, macro_only) train on the same prior, chosen from the same pairs and runs, so the
choice is made once and written to ``prior_choice.json`` in the policy folder (``CHOICE_FILE``:
the family, its parameters, and what the policy manifests record, every candidate's figures
included); each policy stage reads it (``policy.stage.stage_prior``), and so does the joint
refinement (``pipeline.refinement.refine_prior``). The pipeline makes it in a stage of its
own (``choose_prior``), beside the generator's training: it reads only the ground truth. A
stage run alone (``train-policy``) makes the file where it is missing.
The chosen family's pairs (its fit's, which the residual's likelihood uses) go beside it
(``PAIRS_FILE``): a Krauss fit alone takes half a minute.

The file records what it was made from: the scenario (its keys the choice reads,
``choice_settings``) and the ground truth's manifest (its SHA-256: the truth's own outputs
map, so a re-simulated truth is another). One made from anything else is stale: a stage
says so in one line and chooses again (``read_choice``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.files import atomic_path, file_sha256, output_record, write_json
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.prior_choice import FittedPrior, with_prior

CHOICE_FILE = "prior_choice.json"
# The chosen family's pairs (observations, accelerations, and where the Krauss fit gives
# them each pair's driver's tau, "tau"), its fit's: the residual's likelihood pairs
# (``policy.residual``), kept so that no stage fits the family again.
PAIRS_FILE = "prior_pairs.npz"
# The families whose prior a choice may set: "auto" (the family) and "krauss" (the relaxation
# the pairs leave at its bound; where they identify it, the file records the fit alone).
CHOSEN = ("auto", "krauss")
# PPO's own settings: the prior alone (the residual at 0) does not read them.
_PPO = tuple(
    f"policy.{key}"
    for key in (
        "objective",
        "eta",
        "horizon",
        "hidden_train",
        "seed",
        "updates",
        "episodes_per_update",
        "epochs",
        "minibatches",
        "lr",
        "gamma",
        "gae_lambda",
        "clip_coef",
        "vf_coef",
        "ent_coef",
        "hidden_size",
        "init_log_std",
        "lr_schedule",
        "micro_pairs",
        "micro_replay",
        "macro_speed_scale_mps",
        "checkpoint_selection",
        "checkpoint_every",
        "safety",
        "episodes",
        "demand_horizon_s",
        "demand_episodes_per_update",
        "collision_penalty",
        "residual_bound_mps2",
        "residual_pairs",
        "driver_follow",  # chosen after the prior, with it (policy.driver_follow)
        "refine_iterations",
        "refine_updates",
        "refine_epochs",
        "refine_lambda_rec",
    )
)
# Scenario keys (dotted: a table or one key) the choice does not read: the label, the
# evaluation, the generator's training, PPO's, and the deployment's methods, IDM
# calibration and FCD length. Every other key is read (the deployment of a prior alone
# reads the rest of [deploy]: its safety layer, floor, drivers, compare interval).
CHOICE_IGNORES = (
    "name",
    "evaluation",
    "generator",
    *_PPO,
    "deploy.methods",
    "deploy.calibration_budget_s",
    "deploy.calibration_evals",
    "deploy.fcd_s",
)
# Keys under ``CHOICE_IGNORES`` read all the same: the run split (the training runs).
CHOICE_READS = ("generator.held_out_fraction",)


def flat_keys(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested table as dotted keys."""
    out: dict[str, Any] = {}
    for key, value in table.items():
        if isinstance(value, dict):
            out.update(flat_keys(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def settings_of(
    scenario: dict[str, Any], ignores: tuple[str, ...], reads: tuple[str, ...] = ()
) -> dict[str, Any]:
    """The dotted keys of ``scenario`` (``to_dict`` or a manifest's copy) outside
    ``ignores`` (or under ``reads``), with their values as a manifest's JSON holds them."""
    flat = flat_keys(json.loads(json.dumps(scenario, default=str)))

    def under(key: str, prefixes: tuple[str, ...]) -> bool:
        return any(key == p or key.startswith(f"{p}.") for p in prefixes)

    return {k: v for k, v in flat.items() if not under(k, ignores) or under(k, reads)}


def choice_settings(scenario: dict[str, Any]) -> dict[str, Any]:
    """The keys of ``scenario`` the choice reads (``CHOICE_IGNORES``, ``CHOICE_READS``)."""
    return settings_of(scenario, CHOICE_IGNORES, CHOICE_READS)


def makes_choice(sc: Any) -> bool:
    """Whether ``sc``'s prior is one a choice sets (``CHOSEN``)."""
    return sc.policy.prior in CHOSEN


def write_choice(
    path: Path,
    sc: Any,
    data: Path,
    fitted: tuple[Any, FittedPrior],
    wall_s: float,
    command: str = "",
) -> dict[str, Any]:
    """``path`` (``CHOICE_FILE``) and the pairs beside it (``PAIRS_FILE``) for the choice
    ``fitted`` (``policy.stage.fit_stage_prior``'s result: the scenario with its family,
    (parameters, manifest record, pairs)) made for ``sc`` on the ground truth in ``data``;
    the record returned."""
    trained, (prior, extra, pairs_in) = fitted
    obs, acc = pairs_in[:2]
    taus = pairs_in[2] if len(pairs_in) > 2 else None
    pairs = path.parent / PAIRS_FILE
    own = {} if taus is None else {"tau": np.asarray(taus)}  # each pair's driver's tau
    with atomic_path(pairs) as tmp, tmp.open("wb") as fh:
        np.savez(fh, obs=np.asarray(obs), acc=np.asarray(acc), **own)
    record = build_manifest(sc, command, stage="choose-prior")
    record.update(
        ground_truth=str(data),
        ground_truth_manifest_sha256=file_sha256(Path(data) / "manifest.json"),
        family=trained.policy.prior,
        params=dict(prior),
        prior=extra["prior"],
        pairs=len(acc),
        timings_s={"choose_prior": round(wall_s, 3)},
        outputs={PAIRS_FILE: output_record(pairs)},  # checked as a stage's (files.py)
    )
    write_json(record, path)
    return record


def stale_reason(record: dict[str, Any], sc: Any, data: Path, path: Path) -> str | None:
    """Why ``record`` (``path``'s) is not the choice for ``sc`` on the ground truth in
    ``data``; None where it is."""
    keys = ("scenario", "ground_truth_manifest_sha256", "family", "params", "prior", "outputs")
    if any(key not in record for key in keys) or not all(
        isinstance(record[key], dict) for key in ("scenario", "params", "outputs")
    ):
        return "not a prior choice of this version"
    have, want = choice_settings(record["scenario"]), choice_settings(sc.to_dict())
    changed = sorted(k for k in have.keys() | want.keys() if have.get(k) != want.get(k))
    if changed:
        more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
        return f"made for other settings ({', '.join(changed[:3])}{more} changed)"
    # A Krauss prior's record keeps the drivers' taus policy.driver_follow draws from.
    taus = record["prior"].get("driver_taus") if isinstance(record["prior"], dict) else None
    krauss = record["family"] == "krauss"
    if krauss and sc.policy.driver_follow != "none" and "levels_s" not in (taus or {}):
        return "made before the drivers' taus were kept (policy.driver_follow draws them)"
    by = sc.policy.driver_follow
    if krauss and by.startswith("by_vtype") and by not in (taus or {}):
        return f"made without each vType's taus (policy.driver_follow = {by!r} draws them)"
    if record["ground_truth_manifest_sha256"] != file_sha256(Path(data) / "manifest.json"):
        return f"made on another ground truth (its manifest.json is not {data}'s)"
    pairs = path.parent / PAIRS_FILE
    want = record["outputs"].get(PAIRS_FILE) or {}
    if not pairs.is_file() or file_sha256(pairs) != want.get("sha256"):
        return f"its pairs, {PAIRS_FILE}, are missing or changed"
    # policy.driver_follow hands each likelihood pair its driver's tau (pair_taus).
    follows = krauss and sc.policy.driver_follow != "none" and (taus or {}).get("levels_s")
    if follows and not _has_pair_taus(pairs):
        return f"made before its pairs, {PAIRS_FILE}, kept their drivers' taus"
    return None


def _has_pair_taus(pairs: Path) -> bool:
    """Whether the pairs file ``pairs`` keeps each pair's driver's tau (a missing or
    unreadable one says no: the choice is made again)."""
    try:
        with np.load(pairs, allow_pickle=False) as z:
            return "tau" in z.files
    except (OSError, ValueError):
        return False


def read_choice(
    path: Path, sc: Any, data: Path, then: str = "choosing the prior again"
) -> dict[str, Any] | None:
    """The choice in ``path`` where it was made for ``sc`` on the ground truth in ``data``;
    None where there is none, or it is stale (said in one line, with what the reader does
    ``then``: it costs a choice, or a fit)."""
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        why: str | None = "unreadable"
    else:
        why = stale_reason(record, sc, data, path) if isinstance(record, dict) else "unreadable"
    if why is None:
        return record
    print(f"{path}: {why}; {then}")
    return None


def choice_result(path: Path) -> Any:
    """What a stage reading ``path`` trains on (the family and its parameters), None
    without a readable one: equal before and after a choice redone, its readers need not
    be (``pipeline.schedule.Stage.result``)."""
    try:
        record = json.loads(Path(path).read_text())
        return [record["family"], record["params"]]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        return None


def apply_choice(record: dict[str, Any], sc: Any, path: Path) -> tuple[Any, FittedPrior]:
    """The choice in ``record`` (``path``'s, fresh: ``read_choice``) as
    ``policy.stage.fit_stage_prior`` returns it: the scenario with the chosen family, (its
    parameters, what the manifest records, the pairs the residual's likelihood uses)."""
    with np.load(path.parent / PAIRS_FILE, allow_pickle=False) as z:
        pairs = (z["obs"], z["acc"], z["tau"] if "tau" in z.files else None)
    params = {k: float(v) for k, v in record["params"].items()}
    return with_prior(sc, record["family"]), (params, {"prior": record["prior"]}, pairs)

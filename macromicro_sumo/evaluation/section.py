"""Evaluation on a section: macro alignment per method, micro consistency, the K estimate.

The ring's protocol carried over to open, multi-lane roads. Held-out snapshots are completed
by the generator (with the estimated hidden count, and with the true one to show what the
estimate costs) and rolled out for ``evaluation.horizon_steps``; observed vehicles replay
their records, hidden ones are driven by the method. Where every scene's estimate equals
its true count (the ring read as a section) the true count's rows (``hidden_count =
"true"`` in every CSV) are the estimated pass's, relabelled, instead of a second pass that
would differ only in the seed (the manifest's ``true_count_rows`` says which). Methods, on
the same scenes:

* ``ground_truth``: the recorded vehicles (whatever model the user's vTypes have);
* ``policy``, ``micro_only``, ``macro_only``: the learned policies (stochastic);
* ``idm_calibrated``: one IDM fitted by least squares to the observed vehicles' data;
* ``idm_true``: each hidden vehicle's own ground-truth IDM parameters (an oracle bound,
  ``evaluation.idm_true``), where the truth records them (a ``[fleet]`` demand); left out
  elsewhere, with the reason in the log and the manifest.

Statistics count every vehicle on the section at every step; spacings are per lane,
front to front, for vehicles with a leader on the section.

What the figures are against (``reference`` in macro_alignment.csv and
micro_consistency.csv):

* a simulated ground truth: macro errors against ``ground_truth``, every recorded vehicle
  of the same scenes (the paper's protocol), and, as ``station_*`` columns, against the
  detectors' interval of each scene (psi: space-mean speed, spacing = 1 / density per lane);
* field data (``data.source = "files"``): the recorded trajectories hold only the observed
  vehicles, so they are no reference for the population. Macro figures are against the
  stations only (the ``station_*`` columns and a ``stations`` row in place of
  ``ground_truth``); the hidden count is the estimated one only (nobody counted the true
  one). Either way micro figures are the held-out observed vehicles' recorded actions.

With ``instrumented.hidden = "snapshot"`` (every vehicle recorded, the ring's protocol) the
scenes are every held-out snapshot at every K of ``generator.hidden_eval``, each with a
fresh random hidden set; macro_alignment.csv pools them and macro_alignment_by_k.csv splits
every row by K (the ring's table: mean-speed error and spacing-std error with their
intervals, speed std, collisions).
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.data.hidden_counts import scenes_hiding
from macromicro_sumo.data.section import (
    PSI_FIELDS,
    SectionSnapshots,
    SectionTruth,
    concat_snapshots,
    hidden_per_snapshot,
    recorded_snapshots,
    snapshots_by_k,
    split_runs,
)
from macromicro_sumo.env.driver_speed import drivers_bank, resolved_entry
from macromicro_sumo.env.rollout import ActionFn, Rollouts, rollout
from macromicro_sumo.env.section import DEFAULT_SAFETY, SectionCore
from macromicro_sumo.env.section_bank import (
    SectionBank,
    build_section_bank,
    recorded_min_gap,
    typical_length,
    typical_vclass,
    with_future,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.driver_follow import held_out_pairs
from macromicro_sumo.evaluation.idm_fit import calibrate_idm
from macromicro_sumo.evaluation.idm_true import (
    true_idm_action,
    true_idm_by_episode,
    true_idm_table,
)
from macromicro_sumo.evaluation.leader_follower_section import section_leader_follower_tests
from macromicro_sumo.evaluation.methods import method_order
from macromicro_sumo.evaluation.micro_data import idm_action, micro_consistency, micro_pairs
from macromicro_sumo.evaluation.statistics import macro_row, paired_bootstrap_ci, samples_frame
from macromicro_sumo.files import (
    prepare_out_dir,
    staging_dir,
    write_csv,
    write_stage_manifest,
)
from macromicro_sumo.generator.section_sampler import generator_completion, k_of
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.agent import policy_action
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.policy.driver_follow import follow_inputs
from macromicro_sumo.policy.rollout import own_taus
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.physics import leader_length_m
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth
from macromicro_sumo.truth.section_macro import k_summary

METHOD_ORDER = method_order("sumo")
REFERENCE_RECORDED = "ground_truth: every recorded vehicle of the scenes (simulated)"
REFERENCE_STATIONS = "stations: each scene's detector interval (field data)"
REFERENCE_MICRO = "held-out observed vehicles' recorded actions"
STATIONS = "stations"  # macro_alignment.csv's reference row on field data
# The evaluation manifest's ``true_count_rows`` where the estimated pass stands for the true one.
TRUE_REUSED = "the estimated pass's: every scene's estimated hidden count is its true one"


def driven_bank(sc, truth, bank: SectionBank, agent, seed: int) -> SectionBank:
    """``bank`` as ``agent`` drives it: with each hidden driver's desired-speed factor where
    the policy was trained with one (``policy.driver_speed``, the quantiles in its
    checkpoint) and each slot's tau where it has a ``driver_tau`` buffer
    (``policy.driver_follow``: the training rollouts' draw, ``follow_inputs``), as in
    training and deployment; unchanged for every other method (the IDM baselines know
    nothing of either). ``sc``: ``policy.driver_entry`` resolved (``resolved_entry``)."""
    quantiles = None if agent is None else getattr(agent, "driver_speed", None)
    if quantiles is not None and sc.policy.driver_speed != "none":
        bank = drivers_bank(sc, truth.section, bank, quantiles.double().numpy(), seed)
    taus = None if agent is None else getattr(agent, "driver_tau", None)
    return bank if taus is None else follow_inputs(bank, None, None, taus.numpy(), seed)[0]


def agent_action(agent, stochastic: bool = True) -> ActionFn:
    """``policy_action`` on the observation with each slot's tau (the core's bank's
    ``driver_tau``, ``driven_bank``) as a trailing column, as the training rollouts hand it
    (``policy.rollout.own_taus``); the observation as it is for an agent without a
    ``driver_tau`` buffer or on a bank without taus."""
    act = policy_action(agent, stochastic)
    reads = getattr(agent, "driver_tau", None) is not None

    def with_taus(core: SectionCore, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return act(core, own_taus(obs, core.bank.driver_tau if reads else None, core.episode), rng)

    return with_taus


def recorded(bank: SectionBank, section: Section, horizon: int, dt: float) -> Rollouts:
    """The ground truth as a rollout: every true vehicle of the scene over the horizon."""
    v = bank.true_speed_mps[:, 1 : horizon + 1]
    lane = bank.true_lane[:, 1 : horizon + 1]
    arc = bank.true_arc_m[:, 1 : horizon + 1]
    # Only the vehicles of the start scene: the rollouts do not insert vehicles that enter
    # during the horizon either.
    ok = bank.true_valid[:, 1 : horizon + 1] & bank.true_valid[:, :1]
    v = np.where(ok, v, np.nan)
    spacing = np.full(v.shape, np.nan)
    for e in range(v.shape[0]):
        for t in range(v.shape[1]):
            idx = np.flatnonzero(ok[e, t])
            if idx.size:
                lead, gap = section_leaders(
                    section, lane[e, t, idx].astype(np.int64), arc[e, t, idx]
                )
                spacing[e, t, idx[lead >= 0]] = gap[lead >= 0]
    v_all = np.where(bank.true_valid[:, :1], bank.true_speed_mps[:, : horizon + 1], np.nan)
    with np.errstate(invalid="ignore"):
        accel = np.diff(v_all, axis=1) / dt
    # The bank does not keep which true vehicles were hidden: none marked.
    unmarked = np.zeros(bank.true_valid[:, 0].shape, dtype=bool)
    return Rollouts(arc, v, spacing, accel, lane, unmarked, 0, 0)


def station_errors(ro: Rollouts, psi: np.ndarray, seed: int) -> dict[str, float]:
    """A rollout against the stations' interval of each of its scenes (``psi``, one row per
    episode): mean speed error [m/s] of the episode means, with a 95% paired-bootstrap
    interval of the signed error, and the ratio of mean spacings (per lane, front to front;
    the stations' is 1 / density)."""
    v_station = psi[:, PSI_FIELDS.index("mean_speed_mps")]
    d_station = psi[:, PSI_FIELDS.index("mean_spacing_m")]
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an episode that ended at once
        v = np.nanmean(ro.speed_mps, axis=(1, 2))
        d = np.nanmean(ro.spacing_m, axis=(1, 2))
    diff = v - v_station
    lo, hi = paired_bootstrap_ci(diff, seed)
    return {
        "station_speed_err_mps": abs(float(np.nanmean(diff))),
        "station_speed_err_ci_lo_mps": lo,
        "station_speed_err_ci_hi_mps": hi,
        "station_spacing_ratio": float(np.nanmean(d) / np.nanmean(d_station)),
    }


def stations_row(labels: dict[str, Any], psi: np.ndarray) -> dict[str, Any]:
    """The stations' own figures over the scenes: macro_alignment.csv's reference row on
    field data (means only: stations measure no spread)."""
    return {
        **labels,
        "method": STATIONS,
        "mean_speed_mps": float(np.nanmean(psi[:, PSI_FIELDS.index("mean_speed_mps")])),
        "mean_spacing_m": float(np.nanmean(psi[:, PSI_FIELDS.index("mean_spacing_m")])),
        "episodes": len(psi),
    }


# --------------------------------------------------------------------------- the stage


def held_out_scenes(
    sc, truth: SectionTruth, held: np.ndarray, horizon: int, hidden: list[int] | None = None
) -> tuple[SectionSnapshots, dict[int, range] | None]:
    """The evaluation's scenes, and with ``instrumented.hidden = "snapshot"`` the episodes of
    each K: every held-out snapshot with a recorded future at every K of
    ``generator.hidden_eval``, a fresh hidden set each (``data.section.snapshots_by_k``),
    one K after the other. ``hidden`` (``evaluate --hidden``): only the scenes hiding
    those K, on any road (``data.hidden_counts.scenes_hiding``), split by K."""
    lo, hi = sc.generator.hidden_eval
    recorded_ = recorded_snapshots(truth, sc, held)
    if hidden:
        chosen, ranges = scenes_hiding(
            sc, recorded_, hidden, f"the held-out runs of {truth.folder}", lowest=1
        )
        by_k = {k: chosen.take(np.arange(r.start, r.stop)) for k, r in ranges.items()}
        lo = min(hidden)
    elif not hidden_per_snapshot(sc):
        return recorded_, None  # the instrumented vehicles observed: no hidden sets to draw
    else:
        by_k = snapshots_by_k(recorded_, range(lo, hi + 1), sc.seed)
    parts, episodes, start = [], {}, 0
    for k, snaps in by_k.items():
        snaps = snaps.take(with_future(truth, snaps, horizon, sc.simulation.step_length_s))
        if len(snaps):
            parts.append(snaps)
            episodes[k] = range(start, start + len(snaps))
            start += len(snaps)
    if not parts:
        raise UserError(
            f"{truth.folder}: no held-out snapshot has {lo} vehicles to hide and {horizon} "
            f"recorded steps after it (generator.hidden_eval = [{lo}, {hi}] or --hidden)"
        )
    return concat_snapshots(parts), episodes


def _concat(parts: list[Rollouts]) -> Rollouts:
    """Rollouts of one core's episodes, one part after the other (counts summed)."""
    arrays = ("arc_m", "speed_mps", "spacing_m", "accel_mps2", "lane", "hidden")
    return Rollouts(
        *(np.concatenate([getattr(p, a) for p in parts]) for a in arrays),
        sum(p.collisions for p in parts),
        sum(p.errors for p in parts),
    )


def _relabel(part: dict[str, Any] | pd.DataFrame, label: str) -> dict[str, Any] | pd.DataFrame:
    """A row (dict) or samples frame of one pass under another ``hidden_count`` label."""
    if isinstance(part, pd.DataFrame):
        return part.assign(hidden_count=label)
    return part | {"hidden_count": label}


def _episodes(ro: Rollouts, eps: range) -> Rollouts:
    """The episodes ``eps`` of ``ro`` (the recording: no collisions to split)."""
    arrays = ("arc_m", "speed_mps", "spacing_m", "accel_mps2", "lane", "hidden")
    return Rollouts(*(getattr(ro, a)[eps.start : eps.stop] for a in arrays), 0, ro.errors)


def scenario_safety(sc) -> str:
    """The hidden vehicles' safety layer of the evaluation's rollouts: the scenario's
    ``policy.safety``, as in training (``env.slot_core``)."""
    return getattr(sc.policy, "safety", DEFAULT_SAFETY)


def _run(
    sc,
    truth: SectionTruth,
    bank: SectionBank,
    net_file: Path,
    vclass: str,
    act: ActionFn,
    horizon: int,
    seed: int,
    safety: str | None = None,
    by_k: dict[int, range] | None = None,
) -> tuple[Rollouts, dict[str, Any], dict[int, Rollouts]]:
    """One method's rollouts of every episode, safety.csv's figures of them (the
    collisions, how often an observed vehicle left its record, how often the hidden
    vehicles' safety layer capped a command) and, given ``by_k``, the rollouts of each K's
    episodes (seeded ``seed + K``; all of them together are the first). ``safety``: the
    hidden vehicles' safety layer, else the scenario's (``policy.safety``)."""
    safety = safety or scenario_safety(sc)
    core = SectionCore(
        sc,
        truth.section,
        bank,
        net_file,
        seed=sc.seed,
        vclass=vclass,
        safety=safety,
        replay_min_gap_m=recorded_min_gap(truth),
    )
    core.rewarded = False  # the rollouts record states: r_macro would go unread
    per_k: dict[int, Rollouts] = {}
    try:
        if by_k is None:
            ro = rollout(core, act, horizon, seed)
        else:
            per_k = {k: rollout(core, act, horizon, seed + k, eps) for k, eps in by_k.items()}
            ro = _concat(list(per_k.values()))
    finally:
        core.close()
    counts = {"safety": safety, "collisions": ro.collisions, "episodes": len(ro.speed_mps)}
    return ro, counts | core.counts, per_k


def evaluate_section(
    sc,
    data: Path,
    generator: Path,
    policies: dict[str, Path],
    out: Path,
    command: str = "",
    progress: bool = True,
    hidden: list[int] | None = None,
) -> dict[str, Any]:
    """macro_alignment.csv, micro_consistency.csv, k_estimate_summary.csv, samples, FCD and
    a manifest in ``out``; returns the manifest. ``hidden``: only the scenes hiding those
    K (``held_out_scenes``), with a per-K table on any road."""
    t0 = time.perf_counter()
    if "policy" not in policies:
        raise UserError("evaluate needs the trained policy (policy.pt)")
    truth = load_section_truth(data, sc)
    drivers_sc = resolved_entry(sc, truth)[0]  # driver_entry "auto": the train + val runs' rule
    net = load_section_generator(generator, sc)
    agents = {name: load_policy(p, sc) for name, p in policies.items()}
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    held = splits["held_out"]
    h = sc.evaluation.horizon_steps
    snaps, by_k = held_out_scenes(sc, truth, held, h, hidden)
    out = prepare_out_dir(out)  # once the scenes are known to be good
    net_file = scenario_inputs(sc).net_file
    vclass = typical_vclass(truth)
    # The length the IDM subtracts from the observation's leader column: the typical
    # vehicle's where it is the spacing, none where it is the gap (physics.leader_length_m).
    length = typical_length(truth)
    lead_m = leader_length_m(sc.policy.observation, length)
    obs_tr, acc_tr = micro_pairs(sc, truth, np.concatenate([splits["train"], splits["val"]]))
    idm, idm_rmse = calibrate_idm(obs_tr, acc_tr, lead_m)
    oracle, oracle_note = true_idm_table(truth)
    if oracle is None:
        print(oracle_note)
    # The bank's episodes are the snapshots with a recorded future, in order.
    kept = snaps.take(with_future(truth, snaps, h, sc.simulation.step_length_s))
    rows, samples, safety_rows, k_rows = [], [], [], []
    generated: dict[str, dict[str, int]] = {}  # per hidden count: vehicles generated, dropped
    counts = {"estimated": snaps.k_est, "true": snaps.k_true}
    sources = {"estimated": "estimate", "true": "truth"}  # report label -> k_source
    field = sc.data.source == "files"
    # Where every scene's estimated K is its true K (a closed road whose detectors count
    # every vehicle, e.g. the ring) the two passes would complete the same scenes with the
    # same counts, differing only in the seed: the estimated pass's figures stand for both.
    same_k = not field and np.array_equal(k_of(snaps, "estimate"), k_of(snaps, "truth"))
    if field or same_k:  # the true hidden count of field data is unknown
        sources.pop("true")
    n_methods = len(agents) + 1 + (oracle is not None)  # the learned ones, idm_calibrated, idm_true
    bar = tqdm(
        total=len(sources) * (n_methods + 1), desc="evaluate", unit="rollout", disable=not progress
    )
    with staging_dir(out) as stage:
        fcd = stage / "fcd"
        fcd.mkdir()
        for label, source in sources.items():
            seed = sc.seed + 100 + (label == "true")
            complete = generator_completion(net, truth.section, sc, source, seed, length)
            gen_bank = build_section_bank(sc, truth, snaps, complete, horizon=h)
            # Stage I's last check (generator.section_pairs) drops a vehicle it cannot fit
            generated[label] = {"generated": complete.generated, "dropped": complete.dropped}
            labels = {"hidden_count": label}
            if field:
                ref = None
                rows.append(stations_row(labels, gen_bank.psi))
            else:
                ref = recorded(gen_bank, truth.section, h, sc.simulation.step_length_s)
                rows.append(
                    macro_row(labels, "ground_truth", ref, ref, sc.seed)
                    | station_errors(ref, gen_bank.psi, sc.seed)
                )
                samples.append(samples_frame({"K": np.nan, **labels}, "ground_truth", ref))
                for k, eps in (by_k or {}).items():
                    ref_k = _episodes(ref, eps)
                    k_rows.append(
                        macro_row(labels | {"K": k}, "ground_truth", ref_k, ref_k, sc.seed + k)
                    )
            bar.update()
            methods: dict[str, ActionFn] = {n: agent_action(a) for n, a in agents.items()}
            methods["idm_calibrated"] = idm_action(lambda core: idm, lead_m)
            if oracle is not None:
                params = true_idm_by_episode(truth, oracle, kept, gen_bank)
                methods["idm_true"] = true_idm_action(params, lead_m)
            for name in [m for m in METHOD_ORDER if m in methods]:
                bank = driven_bank(drivers_sc, truth, gen_bank, agents.get(name), seed)
                ro, counts_, per_k = _run(
                    sc, truth, bank, net_file, vclass, methods[name], h, seed, by_k=by_k
                )
                safety_rows.append({"hidden_count": label, "method": name, **counts_})
                for k, ro_k in per_k.items():
                    ref_k = None if ref is None else _episodes(ref, by_k[k])
                    k_rows.append(macro_row(labels | {"K": k}, name, ro_k, ref_k, sc.seed + k))
                if name == "policy" and counts_["safety"] != "none":
                    # What the safety layer hides: the policy alone on the same scenes.
                    _, alone, _ = _run(
                        sc, truth, bank, net_file, vclass, methods[name], h, seed, "none"
                    )
                    safety_rows.append({"hidden_count": label, "method": name, **alone})
                if sc.evaluation.fcd_episodes > 0 and label == "estimated":
                    core = SectionCore(
                        sc,
                        truth.section,
                        bank,
                        net_file,
                        seed=sc.seed,
                        fcd_file=fcd / f"{name}.fcd.xml",
                        vclass=vclass,
                        safety=scenario_safety(sc),
                        replay_min_gap_m=recorded_min_gap(truth),
                    )
                    try:
                        rollout(
                            core,
                            methods[name],
                            h,
                            seed,
                            range(min(sc.evaluation.fcd_episodes, len(gen_bank))),
                        )
                    finally:
                        core.close()
                rows.append(
                    macro_row(labels, name, ro, ref, sc.seed)
                    | station_errors(ro, gen_bank.psi, sc.seed)
                )
                samples.append(samples_frame({"K": np.nan, "hidden_count": label}, name, ro))
                bar.update()
        bar.close()
        if same_k:  # the true count's rows: the estimated pass's, relabelled
            rows, samples, safety_rows, k_rows = (
                part + [_relabel(x, "true") for x in part]
                for part in (rows, samples, safety_rows, k_rows)
            )
        align = pd.DataFrame(rows)
        align.insert(1, "mean_k", [float(np.mean(counts[r])) for r in align["hidden_count"]])
        align.insert(2, "reference", REFERENCE_STATIONS if field else REFERENCE_RECORDED)
        write_csv(align, stage / "macro_alignment.csv")
        if by_k is not None:  # the per-K table (instrumented.hidden = "snapshot", --hidden)
            by_k_table = pd.DataFrame(k_rows)
            by_k_table.insert(2, "reference", REFERENCE_STATIONS if field else REFERENCE_RECORDED)
            write_csv(by_k_table, stage / "macro_alignment_by_k.csv")
        write_csv(pd.concat(samples, ignore_index=True), stage / "eval_samples.csv")
        write_csv(pd.DataFrame(safety_rows), stage / "safety.csv")
        obs_ho, acc_ho, taus, later, tau_record = held_out_pairs(sc, truth, held, agents, lead_m)
        idms = {"idm_calibrated": idm}
        micro = micro_consistency(agents, idms, obs_ho, acc_ho, sc, lead_m, taus, later)
        micro.insert(0, "reference", REFERENCE_MICRO)
        write_csv(micro, stage / "micro_consistency.csv")
        lf = section_leader_follower_tests(sc, truth, net_file, agents, idm, length, vclass)
        if not lf.skipped:
            write_csv(lf.traces, stage / "leader_follower.csv")
            write_csv(lf.summary, stage / "leader_follower_summary.csv")
        print(lf.message)
        ks = k_summary(truth.k_estimate, truth.section)
        ks_held = k_summary(truth.k_estimate[truth.k_estimate["run"].isin(held)], truth.section)
        write_csv(
            pd.DataFrame([{"runs": "all", **ks}, {"runs": "held_out", **ks_held}]),
            stage / "k_estimate_summary.csv",
        )
        manifest = build_manifest(sc, command, stage="evaluate")
        manifest.update(
            ground_truth=str(data),
            generator=str(generator),
            policies={k: str(v) for k, v in policies.items()},
            held_out_runs=[int(r) for r in held],
            episodes=len(snaps),
            hidden=sc.instrumented.hidden,
            micro_pair_taus=tau_record or None,
            episodes_by_k={str(k): len(eps) for k, eps in (by_k or {}).items()},
            hidden_counts=sorted(hidden) if hidden else "all",
            true_count_rows=TRUE_REUSED if same_k else ("none" if field else "own pass"),
            data_source=sc.data.source,
            references={
                "macro": REFERENCE_STATIONS if field else REFERENCE_RECORDED,
                "macro_station_columns": "station_*: each scene's detector interval (psi)",
                "micro": REFERENCE_MICRO,
            },
            safety=scenario_safety(sc),
            idm_calibrated=idm.as_dict() | {"fit_rmse_mps2": idm_rmse},
            idm_true=oracle_note,
            k_estimate=ks,
            generated_vehicles=generated,
            leader_follower={"message": lf.message, "reference": lf.reference},
            timings_s={"evaluate": round(time.perf_counter() - t0, 3)},
        )
        outputs = [p.name for p in stage.iterdir() if p.is_file()]
        write_stage_manifest(manifest, stage, "evaluation_manifest.json", outputs)
    return manifest

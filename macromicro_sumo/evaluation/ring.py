"""Evaluation: macro alignment per K and method, micro consistency, on held-out runs.

The paper's protocol, measured in SUMO: for each K, the held-out snapshots are completed
(by the generator, or, for ``ground_truth``, with the true hidden vehicles) and rolled out
for ``evaluation.horizon_steps``; observed vehicles replay their recorded speeds (except
where that would run them into a generated leader: ``env.ring.keep_clear``, counted in the
``replay_overrides`` columns) and the hidden ones are driven by the method, under the
scenario's safety layer (``policy.safety``: ``env.ring.safety_cap``, counted in the
``safety_capped`` columns; the recording, ``ground_truth``, replays without it). All methods
run on the same scenes:

* ``ground_truth``: the recorded fleet (true scene, hidden vehicles apply their recorded actions);
* ``policy``, ``micro_only``, ``macro_only``: the learned policies (stochastic);
* ``idm_calibrated``: one IDM fitted by least squares to the observed vehicles' data;
* ``idm_true``: each hidden vehicle's own ground-truth IDM parameters (an oracle bound),
  given to the generated vehicle it is matched to (least position + speed error).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.optimize import linear_sum_assignment

from macromicro_sumo.data.ring import GroundTruth, load_ground_truth, run_arrays, split_runs
from macromicro_sumo.env.ring import EpisodeBank, RingCore, build_bank, generator_completion
from macromicro_sumo.env.rollout import ActionFn, rollout
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.idm_fit import IdmParams, calibrate_idm, idm_policy_accel
from macromicro_sumo.evaluation.leader_follower import (
    LeaderProfile,
    idm_follower,
    mean_idm_params,
    policy_follower,
    run_leader_follower,
)
from macromicro_sumo.evaluation.methods import method_order
from macromicro_sumo.evaluation.statistics import macro_row, samples_frame
from macromicro_sumo.files import (
    prepare_out_dir,
    staging_dir,
    write_csv,
    write_stage_manifest,
)
from macromicro_sumo.generator.ring_train import load_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.policy.agent import policy_action
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.physics import lookahead_features
from macromicro_sumo.road.ring import read_ring
from macromicro_sumo.scenario.ring import Scenario


def recorded_action(core: RingCore, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The hidden vehicles' recorded actions (with the true scene: the ground truth itself)."""
    return core.bank.gt_accel_mps2[core.episode, core.t][core.hidden]


def idm_action(params: Callable[[RingCore], IdmParams], veh_length_m: float) -> ActionFn:
    def act(core: RingCore, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return idm_policy_accel(obs[core.hidden], params(core), veh_length_m)

    return act


def true_idm_params(
    sc: Scenario, gt: GroundTruth, bank: EpisodeBank
) -> Callable[[RingCore], IdmParams]:
    """Per episode, the true IDM parameters of the hidden vehicles, matched to generated ones."""
    veh = gt.vehicles.set_index(["run", "vehicle_id"])
    n = bank.arc0_m.shape[1]
    ids = [f"v{i}" for i in range(n)]
    cache: dict[int, IdmParams] = {}
    length = sc.network.length_m

    def params(core: RingCore) -> IdmParams:
        ep = core.episode
        if ep not in cache:
            hid = np.flatnonzero(bank.hidden[ep])
            true_arc, gen_arc = bank.true_arc0_m[ep, hid], bank.arc0_m[ep, hid]
            cost = np.abs(
                np.mod(gen_arc[:, None] - true_arc[None, :] + length / 2, length) - length / 2
            )
            _, col = linear_sum_assignment(cost)
            rows = veh.loc[[(bank.run[ep], ids[hid[c]]) for c in col]]
            cache[ep] = IdmParams(
                rows["speed_factor"].to_numpy(),
                rows["tau_s"].to_numpy(),
                rows["accel_mps2"].to_numpy(),
                rows["decel_mps2"].to_numpy(),
                rows["min_gap_m"].to_numpy(),
                float(rows["delta"].iloc[0]),
            )
        return cache[ep]

    return params


def micro_pairs(sc: Scenario, gt: GroundTruth, runs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(observation, recorded action) of every vehicle-step of ``runs``: the micro data,
    with the same features as the env's observations (``policy.observation``)."""
    t = gt.trajectories[gt.trajectories["run"].isin(runs)]
    cols = [
        t["speed_mps"],
        t["speed_limit_mps"],
        t["spacing_m"],
        t["speed_mps"] - t["leader_speed_mps"],
    ]
    if sc.policy.observation == "lookahead":
        geo = read_ring(sc.resolve(sc.network.net_file))
        lim = gt.speed_limits.pivot(index="run", columns="edge_id", values="speed_limit_mps")[
            list(geo.edge_ids)
        ]
        arc = t["arc_pos_m"].to_numpy()
        edge = geo.edge_index(arc)
        limits = lim.loc[t["run"]].to_numpy()
        cols += list(lookahead_features(arc, edge, geo.offsets_m, geo.lengths_m, limits))
    return np.stack(cols, axis=1).astype(np.float64), t["accel_mps2"].to_numpy()


def micro_consistency(
    agents: dict,
    idms: dict[str, IdmParams],
    obs: np.ndarray,
    accel: np.ndarray,
    sc,
    veh_length_m: float | None = None,
) -> pd.DataFrame:
    """Held-out observed actions: NLL under each learned policy, action RMSE for every method.

    ``veh_length_m``: the leader length IDM subtracts (default: the ring fleet's)."""
    length = sc.fleet.length_m if veh_length_m is None else veh_length_m
    a_min, a_max = sc.bounds.accel_mps2
    u = np.clip(accel, a_min, a_max)
    rows = []
    o = torch.as_tensor(obs, dtype=torch.float32)
    for name, agent in agents.items():
        with torch.no_grad():
            d = agent.dist(o)
            nll = float(-d.log_prob(torch.as_tensor(u, dtype=torch.float32)).mean())
            rmse = float(np.sqrt(np.mean((np.clip(d.mean.numpy(), a_min, a_max) - u) ** 2)))
        rows.append({"method": name, "nll": nll, "action_rmse_mps2": rmse, "n_pairs": len(u)})
    for name, p in idms.items():
        pred = np.clip(idm_policy_accel(obs, p, length), a_min, a_max)
        rows.append(
            {
                "method": name,
                "nll": np.nan,
                "action_rmse_mps2": float(np.sqrt(np.mean((pred - u) ** 2))),
                "n_pairs": len(u),
            }
        )
    return pd.DataFrame(rows)


def long_rollout_bank(
    sc: Scenario, gt: GroundTruth, run: int, seconds: float, k: int, complete_fn, seed: int
) -> EpisodeBank:
    """One long episode from the start of a held-out run (time-space diagrams)."""
    times, _, _, _ = run_arrays(gt.trajectories, run)
    steps = min(int(round(seconds / sc.simulation.step_length_s)), len(times) - 2)
    bank = build_bank(sc, gt, np.array([run]), complete_fn, k, seed, horizon=steps)
    first = int(np.argmin(bank.time_s))
    return bank.take(np.array([first]))


# --------------------------------------------------------------------------- the stage

METHOD_ORDER = method_order("ring")


def macro_alignment(
    sc: Scenario,
    gt: GroundTruth,
    net,
    agents: dict,
    idm_cal: IdmParams | None,
    runs: np.ndarray,
    ks: list[int],
    fcd_dir: Path | None = None,
    progress: bool = False,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """macro_alignment.csv and eval_samples.csv: every method on the same scenes of ``runs``.

    Per K, the snapshots are completed ``evaluation.completions_per_scene`` times by the
    generator, draw m seeded ``seed + 10_000 m`` (the episodes of draw 0 first), and the
    true scenes' rollout (``ground_truth``, the recording) is repeated as often, so that
    episodes pair up one to one;
    each method's rollout draws from its own generator seeded ``seed + 100 + K``, so a
    method's rows do not depend on which other methods run (``idm_cal`` None leaves out
    ``idm_calibrated``). FCD of the first ``evaluation.fcd_episodes`` episodes goes to
    ``fcd_dir`` when given.
    """
    h = sc.evaluation.horizon_steps
    names = [
        m
        for m in METHOD_ORDER
        if m in agents or m in ("ground_truth", "idm_true") or (m == "idm_calibrated" and idm_cal)
    ]
    rows, samples = [], []
    bar = tqdm(total=len(ks) * len(names), desc="evaluate", unit="rollout", disable=not progress)
    for k in ks:
        seed = sc.seed + 100 + k
        draws = range(sc.evaluation.completions_per_scene)
        true_bank = build_bank(sc, gt, runs, lambda s: (s.arc_m, s.speed_mps), k, seed, horizon=h)
        first = build_bank(sc, gt, runs, generator_completion(net, sc, seed), k, seed, horizon=h)
        gen_bank = EpisodeBank.concat(
            [first]
            + [
                first.completed_again(
                    generator_completion(net, sc, seed + 10_000 * m), sc.network.length_m
                )
                for m in draws[1:]
            ]
        )
        methods: dict[str, tuple[EpisodeBank, ActionFn]] = {
            "ground_truth": (true_bank, recorded_action)
        }
        for name, agent in agents.items():
            methods[name] = (gen_bank, policy_action(agent))
        if idm_cal is not None:
            methods["idm_calibrated"] = (
                gen_bank,
                idm_action(lambda core: idm_cal, sc.fleet.length_m),
            )
        methods["idm_true"] = (
            gen_bank,
            idm_action(true_idm_params(sc, gt, gen_bank), sc.fleet.length_m),
        )
        ref = None
        for name in [m for m in METHOD_ORDER if m in methods]:
            bank, act = methods[name]
            safety = "none" if name == "ground_truth" else sc.policy.safety
            core = RingCore(sc, bank, seed=sc.seed, safety=safety)
            try:
                ro = rollout(core, act, h, seed)
            finally:
                core.close()
            # Observed vehicles that left their record to keep clear of a generated leader
            # (``env.ring.keep_clear``) and hidden vehicles' commands the safety layer capped
            # (``env.ring.safety_cap``): vehicle-steps and episodes, on record beside the
            # collisions they stand in for.
            overrides = {
                "replay_overrides": core.replay_overrides,
                "replay_override_episodes": len(core.overridden_episodes),
                "safety_capped": core.safety_capped,
                "safety_capped_episodes": len(core.capped_episodes),
                "hidden_steps": core.hidden_steps,
            }
            if name == "ground_truth":  # the recording: the same for every draw, replayed once
                ro = ro.repeated(len(draws))
                overrides = {key: val * len(draws) for key, val in overrides.items()}
            overrides["safety"] = safety
            overrides["safety_capped_share"] = core.safety_capped / max(core.hidden_steps, 1)
            if fcd_dir is not None and sc.evaluation.fcd_episodes > 0:
                fcd = fcd_dir / f"{name}_K{k}.fcd.xml"
                core = RingCore(sc, bank, seed=sc.seed, fcd_file=fcd, safety=safety)
                try:
                    rollout(core, act, h, seed, range(min(sc.evaluation.fcd_episodes, len(bank))))
                finally:
                    core.close()
            ref = ro if name == "ground_truth" else ref
            rows.append({**macro_row({"K": k}, name, ro, ref, seed), **overrides})
            samples.append(samples_frame({"K": k}, name, ro))
            bar.update()
    bar.close()
    return pd.DataFrame(rows), pd.concat(samples, ignore_index=True)


def evaluate(
    sc: Scenario,
    data: Path,
    generator: Path,
    policies: dict[str, Path],
    out: Path,
    command: str = "",
    progress: bool = True,
    hidden: list[int] | None = None,
) -> dict:
    """Write macro_alignment.csv, micro_consistency.csv, leader_follower*.csv, samples,
    FCD files and an evaluation manifest into ``out``; returns the manifest."""
    import time

    t0 = time.perf_counter()
    if "policy" not in policies:
        raise UserError("evaluate needs the trained policy (policy.pt)")
    n = sc.fleet.n_vehicles
    for k in hidden or []:
        if not 1 <= k <= n - 1:
            raise UserError(
                f"--hidden {k}: K must be in [1, {n - 1}] (N = fleet.n_vehicles = {n} of {sc.source}; "
                "at least one vehicle must be observed)"
            )
    for name, path in policies.items():
        if not Path(path).is_file():
            raise UserError(
                f"{path}: {name} checkpoint not found (run `macromicro train-policy` first)"
            )
    net = load_generator(generator, sc)
    agents = {name: load_policy(path, sc) for name, path in policies.items()}
    gt = load_ground_truth(data, sc)
    out = prepare_out_dir(out)
    torch.set_num_threads(1)
    splits = split_runs(gt.runs, sc.generator.held_out_fraction, sc.seed)
    fit_obs, fit_acc = micro_pairs(sc, gt, np.concatenate([splits["train"], splits["val"]]))
    idm_cal, idm_rmse = calibrate_idm(fit_obs, fit_acc, sc.fleet.length_m, sc.fleet.delta)
    h = sc.evaluation.horizon_steps
    ks = hidden or list(range(sc.generator.hidden_eval[0], sc.generator.hidden_eval[1] + 1))
    with staging_dir(out) as stage:
        (stage / "fcd").mkdir()
        align, samples = macro_alignment(
            sc, gt, net, agents, idm_cal, splits["held_out"], ks, stage / "fcd", progress
        )
        write_csv(align, stage / "macro_alignment.csv")
        write_csv(samples, stage / "eval_samples.csv")
        held_obs, held_acc = micro_pairs(sc, gt, splits["held_out"])
        micro = micro_consistency(agents, {"idm_calibrated": idm_cal}, held_obs, held_acc, sc)
        write_csv(micro, stage / "micro_consistency.csv")
        write_csv(
            timespace(sc, gt, splits["held_out"], net, agents["policy"]), stage / "timespace.csv"
        )
        lf_traces, lf_summary = leader_follower_tests(sc, agents, idm_cal)
        write_csv(lf_traces, stage / "leader_follower.csv")
        write_csv(lf_summary, stage / "leader_follower_summary.csv")
        manifest = build_manifest(sc, command, stage="evaluate")
        manifest.update(
            idm_calibrated={**idm_cal.as_dict(), "fit_rmse_mps2": idm_rmse},
            horizon_steps=h,
            policies={k: str(v) for k, v in policies.items()},
            generator=str(generator),
            ground_truth=str(data),
            timings_s={"evaluate": round(time.perf_counter() - t0, 3)},
        )
        outputs = [p.name for p in stage.iterdir() if p.is_file()]
        write_stage_manifest(manifest, stage, "evaluation_manifest.json", outputs)
    return manifest


def timespace(sc: Scenario, gt: GroundTruth, runs: np.ndarray, net, agent) -> pd.DataFrame:
    """Long rollouts from the start of the first held-out run: ground truth vs policy (K = N - 1)."""
    k = min(sc.generator.hidden_eval[1], sc.fleet.n_vehicles - 1)
    frames = []
    for name, complete_fn, act in (
        ("ground_truth", lambda s: (s.arc_m, s.speed_mps), recorded_action),
        ("policy", generator_completion(net, sc, sc.seed), policy_action(agent)),
    ):
        bank = long_rollout_bank(
            sc, gt, int(runs[0]), sc.evaluation.timespace_s, k, complete_fn, sc.seed
        )
        safety = "none" if name == "ground_truth" else sc.policy.safety
        core = RingCore(sc, bank, seed=sc.seed, safety=safety)
        try:
            steps = bank.replay_speed_mps.shape[1] - 1
            ro = rollout(core, act, steps, sc.seed)
        finally:
            core.close()
        e, t, n = ro.arc_m.shape
        frames.append(
            pd.DataFrame(
                {
                    "method": name,
                    "time_s": np.repeat((np.arange(t) + 1) * sc.simulation.step_length_s, n),
                    "vehicle_id": np.tile([f"veh{i}" for i in range(n)], t),
                    "hidden": np.tile(bank.hidden[0], t).astype(int),
                    "arc_pos_m": ro.arc_m[0].ravel(),
                    "speed_mps": ro.speed_mps[0].ravel(),
                }
            )
        )
    return pd.concat(frames, ignore_index=True).dropna()


def leader_follower_tests(
    sc: Scenario, agents: dict, idm_cal: IdmParams
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The paper's Fig. 3 tests for every learned method and the calibrated IDM."""
    followers = {name: policy_follower(agent) for name, agent in agents.items()}
    cal = {k: float(v) for k, v in idm_cal.as_dict().items()}
    followers["idm_calibrated"] = idm_follower(cal, sc.fleet.length_m)
    duration = sc.evaluation.lf_duration_s
    profile = LeaderProfile(duration_s=duration, hold_s=min(20.0, duration / 3))
    return run_leader_follower(
        sc, followers, mean_idm_params(sc), sc.evaluation.lf_trials, sc.seed, profile
    )

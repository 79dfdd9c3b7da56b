"""Stage II: PPO for the shared policy, J(theta) = E[r_micro + eta r_macro] (paper, Alg. 1).

Read top to bottom as CleanRL's ppo_continuous_action: rollout, GAE, update (the agent is
``policy.agent``, its checkpoints ``policy.checkpoint``, the CLI stage ``policy.stage``).

* The policy is a Gaussian over the acceleration with a state-independent std; the env
  clips the sample to [a_min, a_max]. One policy drives every hidden vehicle.
* r_macro enters through the policy gradient: each hidden vehicle's reward is
  eta * r_macro,t (shared), with a value baseline, GAE and the clipped surrogate.
* r_micro = sum log pi(u | o) over observed vehicles depends on theta directly, so it is a
  likelihood term of the loss on the observed (o, u) pairs: its gradient is exact. Both
  terms are averaged per vehicle-step, so eta keeps its meaning as the macro weight.
  Advantages are normalised only when there is no likelihood term (macro_only).
* With ``policy.prior`` (a residual policy) the likelihood's pairs are the recorded ones
  the prior was fitted on (``recorded_pairs``), the residual is fitted only where a leader
  changes the prior's action and (``policy.residual_pairs``) not on pairs held back far
  below it, and anchors hold it at 0 off its pairs and, where the truth has a warm-up, at
  the warm-up's states off them (``policy.residual``: why, measured).
* Ablations (``policy.objective``): ``mix`` (the paper), ``micro_only`` (eta = 0: behaviour
  cloning), ``macro_only`` (no likelihood term). An empty minibatch (few samples) is skipped.
* The env core is a section's ``SectionCore`` (``make_core``; the paper's ring is one); on
  a ring the updates' rollouts run on a ``BatchedSectionCore`` (``policy.rollout``).
  On a section vehicles leave mid-episode and recorded actions can be unknown: steps of an
  inactive vehicle carry no loss (its value target ends there), NaN actions no likelihood.
  Observations are normalised with the mean/std of the bank's initial observations
  (agent buffers, in the checkpoint).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import nn

from macromicro_sumo.checkpoints import save_torch
from macromicro_sumo.env.batched import batched_like
from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.observation import bank_shift_scale
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.env.section_observations import initial_observations
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import write_csv
from macromicro_sumo.policy.agent import Agent, mean_logp, mean_rmse
from macromicro_sumo.policy.checkpoint import (
    CHECKPOINT_FORMAT,
    policy_file,
    resumable_checkpoint,
    signature,
)
from macromicro_sumo.policy.demand_rollout import (
    collect_demand,
    demand_log,
    join_demand,
    prior_warmup_states,
)
from macromicro_sumo.policy.driver_follow import follow_inputs
from macromicro_sumo.policy.prior_choice import LikelihoodPairs
from macromicro_sumo.policy.residual import (
    anchor_loss,
    anchor_observations,
    drops_held_pairs,
    off_support,
    residual_pairs,
    warmup_anchor_loss,
)
from macromicro_sumo.policy.rollout import Rollout, collect, collect_batched
from macromicro_sumo.progress import tqdm
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section


def gae(
    rewards: np.ndarray, values: np.ndarray, gamma: float, lam: float
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation along axis 0 for episodes that end after the last step.

    ``rewards`` and ``values`` are (T, ...); returns (advantages, returns) of the same shape.
    """
    adv = np.zeros_like(rewards)
    last = np.zeros_like(rewards[0])
    for t in reversed(range(len(rewards))):
        next_v = values[t + 1] if t + 1 < len(rewards) else 0.0
        delta = rewards[t] + gamma * next_v - values[t]
        last = delta + gamma * lam * last
        adv[t] = last
    return adv, adv + values


def clipped_actions(actions: np.ndarray, a_min: float, a_max: float) -> tuple[np.ndarray, float]:
    """Ground-truth actions clipped to the bounds for the likelihood, and the clipped share."""
    out = np.clip(actions, a_min, a_max)
    return out, float((out != actions).mean()) if actions.size else 0.0


Core = SectionCore
BATCH_SCENES = 64  # the batched core's scenes: episodes of an update per SUMO step
WARMUP_SEED_OFFSET = 7919  # the warm-up anchors' generator: seed + this


def warmup_anchors(sc: SectionScenario, use_micro: bool) -> bool:
    """Whether the residual gets warm-up anchors (``policy.residual``): a residual policy
    with a likelihood term, on a simulated ground truth with a warm-up."""
    cfg = sc.policy
    return (
        use_micro
        and cfg.prior != "none"
        and cfg.residual_bound_mps2 > 0
        and sc.data.source != "files"
        and sc.simulation.warmup_s > 0
    )


# --------------------------------------------------------------------------- training


def split_episodes(runs: np.ndarray, val_runs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Episode indices for training and for validation (those of ``val_runs``)."""
    is_val = np.isin(runs, val_runs) if val_runs is not None else np.zeros(len(runs), dtype=bool)
    if is_val.all():
        raise UserError("every episode belongs to a validation run: none is left to train on")
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


def micro_mask(ro: Rollout, observed_leader: bool) -> np.ndarray:
    """(E, H, N) bool: the observed vehicle-steps whose recorded action enters r_micro.

    ``observed_leader`` keeps only vehicles whose leader is observed too: their observation
    is the recorded one, while behind a hidden leader the spacing and v - v_leader come from
    the generator's completion and the policy, so the recorded action answers another state
    (noise in the inputs, which flattens the learned response to spacing and delta_v).
    """
    hid = np.broadcast_to(ro.hidden[:, None, :], ro.actions.shape)
    with np.errstate(invalid="ignore"):
        keep = ~hid & ro.active & np.isfinite(ro.gt_actions)
    return keep & ~ro.leader_hidden if observed_leader else keep


def validation_pairs(
    agent: Agent, core: Core, episodes: np.ndarray, horizon: int, sc: SectionScenario
) -> tuple[torch.Tensor, torch.Tensor]:
    """Observed (o, u) pairs of validation episodes whose observation is recorded.

    Pairs of a vehicle whose leader is observed do not depend on the policy that drives the
    hidden vehicles, so one rollout (with the initial policy) fixes the validation set.
    """
    if len(episodes) == 0:
        return torch.zeros((0, core.obs_dim)), torch.zeros(0)
    ro = collect(agent, core, episodes, 0.0, horizon, torch.Generator().manual_seed(sc.seed + 1))
    keep = micro_mask(ro, observed_leader=True)
    act, _ = clipped_actions(ro.gt_actions[keep], *sc.bounds.accel_mps2)
    return torch.as_tensor(ro.obs[keep]), torch.as_tensor(act, dtype=torch.float32)


def learning_rate(lr: float, schedule: str, update: int, n_updates: int) -> float:
    """Adam's rate at ``update`` (0-based): constant, or linear decay reaching 0 after the last."""
    return lr * (1.0 - update / n_updates) if schedule == "linear" else lr


def train_policy(
    sc: SectionScenario,
    bank: SectionBank,
    out: Path,
    objective: str | None = None,
    resume: bool | str = False,
    progress: bool = True,
    updates: int | None = None,
    run_key: str = "",
    init: dict[str, Any] | None = None,
    make_core: Callable[[Any, int], Core] | None = None,
    val_runs: np.ndarray | None = None,
    make_demand: Callable[[], DemandCore] | None = None,
    prior_params: Mapping[str, float] | None = None,
    recorded_pairs: LikelihoodPairs | tuple[np.ndarray, np.ndarray] | None = None,
    driver_speed: np.ndarray | None = None,
    driver_tau: np.ndarray | None = None,
) -> dict[str, Any]:
    """PPO on the env over ``bank``; writes policy.pt, policy_train_log.csv, checkpoints.

    ``make_demand()`` builds a section's demand episodes (``env.demand``): with
    ``policy.episodes`` = "demand" or "mixed" each update's policy gradient also (or only)
    learns from ``policy.demand_episodes_per_update`` of them (``policy.demand_rollout``);
    the likelihood term keeps the snapshot episodes' recorded pairs.

    ``make_core(bank, seed)`` builds the env core (default: a ``SectionCore`` on the
    scenario's section with SUMO's defaults; ``policy.stage`` passes its own). With ``policy.checkpoint_selection``
    other than "last", the episodes of ``val_runs`` are kept out of training and the policy
    returned and saved is the update's best on them (``mean_logp`` or ``mean_rmse``).

    ``prior_params`` (``policy.prior.PRIOR_KEYS``; ``evaluation.idm_fit.fit_policy_prior``):
    the fitted model under the actor with a ``policy.prior`` (required then), whose residual
    is bounded by ``policy.residual_bound_mps2``; the checkpoints record the prior.
    ``recorded_pairs`` (obs (N, D), accel (N,), and each pair's driver's tau or None:
    ``policy.prior_choice.LikelihoodPairs``): the observed vehicles' recorded pairs, what
    their own sensors saw (the pairs the prior was fitted on): the likelihood term uses them
    instead of the rollouts' observed pairs, whose leader is often a generated vehicle the
    recorded action did not answer (``policy.residual``). ``driver_speed``: the drivers'
    desired-speed factor quantiles (``policy.driver_speed = "drawn"``), kept in the agent;
    ``driver_tau``: the drivers' tau quantiles (``policy.driver_follow``), the same.
    """
    cfg = sc.policy
    objective = objective or cfg.objective
    eta = 0.0 if objective == "micro_only" else sc.policy.eta
    use_micro = objective != "macro_only"
    n_updates = updates or cfg.updates
    if cfg.prior != "none" and prior_params is None:
        raise UserError(f"policy.prior = {cfg.prior!r} needs its fitted parameters (sections only)")
    ckpt_path = out / f"policy_{objective}_checkpoint.pt"
    if make_core is None:
        # The scenario's own section with SUMO's defaults (the stage passes its own core).
        section, net_file = load_section(sc)[1], scenario_inputs(sc).net_file
        make_core = lambda b, seed: SectionCore(sc, section, b, net_file, seed=seed)  # noqa: E731
    seed = sc.seed if cfg.seed < 0 else cfg.seed  # policy.seed: a second training
    # The warm-up's states under the prior, anchors of the residual where they lie off its
    # pairs (policy.residual): the start every deployment drives into. Collected before the
    # snapshot env starts; none without a warm-up (the ring records from its insertion).
    warm = None
    if warmup_anchors(sc, use_micro) and make_demand is not None:
        states = prior_warmup_states(sc, prior_params, make_demand, driver_speed, driver_tau)
        warm = torch.as_tensor(states)
    # policy.driver_follow: each slot's tau, and each likelihood pair's driver's own.
    bank, recorded_pairs = follow_inputs(bank, recorded_pairs, prior_params, driver_tau, seed)
    core = make_core(bank, seed)
    # The ring's rollouts, B episodes per SUMO step: the same rollout, to the bit (rollout.py).
    batched = batched_like(core, min(cfg.episodes_per_update, BATCH_SCENES))
    # Demand episodes only where the policy gradient is used (micro_only has none).
    use_demand = make_demand is not None and cfg.episodes != "snapshots" and eta > 0
    demand = make_demand() if use_demand else None
    t0 = time.perf_counter()
    env_steps = 0
    try:
        shift_scale = bank_shift_scale(initial_observations(sc, core.section, bank))
        torch.manual_seed(seed)
        agent = Agent(
            cfg.hidden_size,
            cfg.init_log_std,
            cfg.observation,
            shift_scale,
            cfg.prior,
            prior_params,
            cfg.residual_bound_mps2,
            driver_speed,
            driver_tau,
        )
        if init is not None:
            agent.load_state_dict(init)
        # macro_only never sees observed actions: choosing its update by them would leak them.
        select = cfg.checkpoint_selection != "last" and objective != "macro_only"
        train_eps, val_eps = split_episodes(bank.run, val_runs if select else None)
        val_obs, val_act = validation_pairs(agent, core, val_eps, cfg.horizon, sc)
        best_val, best_state = -float("inf"), None
        opt = torch.optim.Adam(agent.parameters(), lr=cfg.lr)
        rng = np.random.default_rng([seed, 41])
        gen = torch.Generator().manual_seed(seed)
        # The warm-up anchors' own draws: ``gen``'s stay as they were without them.
        warm_gen = torch.Generator().manual_seed(seed + WARMUP_SEED_OFFSET)
        log: list[dict[str, Any]] = []
        start = 0
        # Observed (o, u) pairs of the last ``micro_replay`` rollouts: the likelihood term is
        # supervised, so pairs of earlier rollouts are as valid as this one's.
        micro_pool: list[tuple[torch.Tensor, torch.Tensor]] = []
        ck = resumable_checkpoint(ckpt_path, sc, run_key, resume)
        if ck is not None:
            agent.load_state_dict(ck["state_dict"])
            opt.load_state_dict(ck["optimizer"])
            rng.bit_generator.state = ck["numpy_rng"]
            gen.set_state(ck["torch_rng"])
            log, start = ck["log"], ck["update"]
            micro_pool = ck.get("micro_pool", [])
            best_val, best_state = ck.get("best_val", best_val), ck.get("best_state_dict")
            if "warmup_rng" in ck:
                warm_gen.set_state(ck["warmup_rng"])
        a_min, a_max = sc.bounds.accel_mps2
        # policy.residual_pairs: held-back pairs out of the residual's likelihood.
        lanes = int(np.max(core.section.n_lanes))
        drop_held = drops_held_pairs(cfg.residual_pairs, core.section.closed, lanes)
        if recorded_pairs is not None:  # the likelihood's pairs, the same every update
            clipped = clipped_actions(recorded_pairs[1], a_min, a_max)[0]
            fixed_pairs = (
                torch.as_tensor(recorded_pairs[0], dtype=torch.float32),
                torch.as_tensor(clipped, dtype=torch.float32),
            )
        bar = tqdm(
            range(start, n_updates),
            desc=f"train-policy ({objective})",
            unit="update",
            disable=not progress,
            initial=start,
            total=n_updates,
        )
        for update in bar:
            opt.param_groups[0]["lr"] = learning_rate(cfg.lr, cfg.lr_schedule, update, n_updates)
            episodes = train_eps[rng.integers(0, len(train_eps), cfg.episodes_per_update)]
            if batched is None:
                ro = collect(agent, core, episodes, eta, cfg.horizon, gen)
            else:
                ro = collect_batched(agent, batched, episodes, eta, cfg.horizon, gen)
            env_steps += cfg.episodes_per_update * cfg.horizon
            # GAE runs along time: (E, H, N) -> (H, E, N) and back. A vehicle's episode ends
            # when it leaves (no reward, value 0 after): the ring's vehicles never do.
            rewards = np.where(ro.active, ro.rewards[..., None], np.float32(0.0))
            values = np.where(ro.active, ro.values, np.float32(0.0))
            adv, ret = gae(
                np.swapaxes(rewards, 0, 1), np.swapaxes(values, 0, 1), cfg.gamma, cfg.gae_lambda
            )
            adv, ret = np.swapaxes(adv, 0, 1), np.swapaxes(ret, 0, 1)
            hid_all = np.broadcast_to(ro.hidden[:, None, :], ro.actions.shape)
            hid = hid_all & ro.active
            obs_pairs = micro_mask(ro, cfg.micro_pairs == "observed_leader")
            t_frac = np.broadcast_to(
                (np.arange(cfg.horizon) / cfg.horizon)[None, :, None], ro.actions.shape
            )
            b_obs = torch.as_tensor(ro.obs[hid])
            b_act, b_logp = torch.as_tensor(ro.actions[hid]), torch.as_tensor(ro.logp[hid])
            b_adv, b_ret = torch.as_tensor(adv[hid]), torch.as_tensor(ret[hid])
            b_t = torch.as_tensor(t_frac[hid], dtype=torch.float32)
            if cfg.episodes == "demand" and demand is not None:  # the snapshots' pairs only
                b_obs, b_act, b_logp, b_adv, b_ret, b_t = (
                    x[:0] for x in (b_obs, b_act, b_logp, b_adv, b_ret, b_t)
                )
            db = None
            if demand is not None:
                windows = demand.windows(rng, cfg.demand_episodes_per_update)
                db = collect_demand(
                    agent,
                    demand,
                    windows,
                    eta,
                    cfg.collision_penalty,
                    cfg.gamma,
                    cfg.gae_lambda,
                    gen,
                )
                b_obs, b_act, b_logp, b_adv, b_ret, b_t = join_demand(
                    (b_obs, b_act, b_logp, b_adv, b_ret, b_t), db
                )
            if not use_micro and len(b_adv) > 1:
                b_adv = (b_adv - b_adv.mean()) / (b_adv.std() + 1e-8)
            gt, clip_share = clipped_actions(ro.gt_actions[obs_pairs], a_min, a_max)
            if recorded_pairs is not None:
                micro_pool = [fixed_pairs]
            else:
                micro_pool.append(
                    (torch.as_tensor(ro.obs[obs_pairs]), torch.as_tensor(gt, dtype=torch.float32))
                )
                del micro_pool[: -cfg.micro_replay]
            m_obs = torch.cat([o for o, _ in micro_pool])
            m_act = torch.cat([a for _, a in micro_pool])
            n_b, n_m = len(b_obs), len(m_obs)
            # A residual is fitted where a leader matters and held at 0 off its pairs
            # (policy.residual): anchors are drawn from every pair's state.
            m_all, support, warm_off = m_obs, None, None
            if agent.prior != "none" and float(agent.residual_bound) > 0 and n_m > 0:
                support, m_obs, m_act = residual_pairs(agent, m_obs, m_act, drop_held)
                n_m = len(m_obs)
                if warm is not None:
                    warm_off = off_support(warm, support, agent.scale)
            stats: dict[str, list[float]] = {
                k: [] for k in ("pg_loss", "v_loss", "entropy", "kl", "micro_logp")
            }
            for _ in range(cfg.epochs):
                perm_b, perm_m = (
                    torch.randperm(n_b, generator=gen),
                    torch.randperm(n_m, generator=gen),
                )
                for j in range(cfg.minibatches):
                    ib = perm_b[j * n_b // cfg.minibatches : (j + 1) * n_b // cfg.minibatches]
                    im = perm_m[j * n_m // cfg.minibatches : (j + 1) * n_m // cfg.minibatches]
                    loss = torch.zeros(())
                    if eta > 0 and len(ib):
                        d = agent.dist(b_obs[ib])
                        new_logp = d.log_prob(b_act[ib])
                        ratio = (new_logp - b_logp[ib]).exp()
                        pg = torch.max(
                            -b_adv[ib] * ratio,
                            -b_adv[ib] * ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef),
                        ).mean()
                        v_loss = 0.5 * ((agent.value(b_obs[ib], b_t[ib]) - b_ret[ib]) ** 2).mean()
                        ent = d.entropy().mean()
                        loss = loss + pg + cfg.vf_coef * v_loss - cfg.ent_coef * ent
                        stats["pg_loss"].append(float(pg.detach()))
                        stats["v_loss"].append(float(v_loss.detach()))
                        stats["entropy"].append(float(ent.detach()))
                        stats["kl"].append(
                            float(((ratio - 1) - (new_logp - b_logp[ib])).mean().detach())
                        )
                    if use_micro and len(im):
                        micro = agent.dist(m_obs[im]).log_prob(m_act[im]).mean()
                        loss = loss - micro
                        stats["micro_logp"].append(float(micro.detach()))
                    if use_micro and support is not None and (len(im) or n_m == 0):
                        # Where no pair is outside the free regime the anchors still hold
                        # the residual: without them the policy gradient alone shaped it,
                        # differently per PPO seed (policy.residual).
                        n_anchors = len(im) or max(1, len(m_all) // cfg.minibatches)
                        pick = torch.randint(len(m_all), (n_anchors,), generator=gen)
                        anchors = anchor_observations(m_all[pick], gen)
                        loss = loss + anchor_loss(agent, anchors, support)
                        if warm_off is not None and len(warm_off):
                            pick = torch.randint(len(warm_off), (n_anchors,), generator=warm_gen)
                            loss = loss + warmup_anchor_loss(agent, warm_off[pick], support)
                    if not loss.requires_grad:
                        continue
                    opt.zero_grad()
                    loss.backward()
                    nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
                    opt.step()
            micro_all = mean_logp(agent, *micro_pool[-1])
            val_logp = mean_logp(agent, val_obs, val_act)
            val_rmse = mean_rmse(agent, val_obs, val_act)
            score = -val_rmse if cfg.checkpoint_selection == "val_micro_rmse" else val_logp
            if score > best_val:  # NaN (no validation pairs) never is: the last one is kept
                best_val, best_state = score, copy.deepcopy(agent.state_dict())
            row = {
                "update": update + 1,
                "env_steps": (update + 1) * cfg.episodes_per_update * cfg.horizon,
                "r_macro": float(ro.r_macro.mean()),
                "r_micro_per_pair": micro_all,
                "val_micro_logp": val_logp,
                "val_micro_rmse_mps2": val_rmse,
                **{k: float(np.mean(v)) if v else float("nan") for k, v in stats.items()},
                "action_std_mps2": float(agent.log_std.detach().exp()),
                "collisions": ro.collisions,
                "sumo_errors": ro.sumo_errors,
                "gt_actions_clipped_share": clip_share,
                **demand_log(db),
                "wall_s": time.perf_counter() - t0,
            }
            log.append(row)
            bar.set_postfix(
                r_macro=f"{row['r_macro']:.4f}", logp=f"{micro_all:.3f}", coll=ro.collisions
            )
            if (update + 1) % cfg.checkpoint_every == 0 or update + 1 == n_updates:
                save_torch(
                    ckpt_path,
                    {
                        "format": CHECKPOINT_FORMAT,
                        "signature": signature(sc),
                        "run_key": run_key,
                        "state_dict": agent.state_dict(),
                        "optimizer": opt.state_dict(),
                        "numpy_rng": rng.bit_generator.state,
                        "torch_rng": gen.get_state(),
                        "update": update + 1,
                        "log": log,
                        "hidden_size": agent.hidden_size,
                        "prior": agent.prior,
                        "driver_speed": getattr(cfg, "driver_speed", "none"),
                        "driver_follow": getattr(cfg, "driver_follow", "none"),
                        "micro_pool": micro_pool,
                        "best_val": best_val,
                        "best_state_dict": best_state,
                        "warmup_rng": warm_gen.get_state(),
                    },
                )
    finally:
        core.close()
        if batched is not None:
            batched.close()
        if demand is not None:
            demand.close()
    if best_state is not None:
        agent.load_state_dict(best_state)
    wall = time.perf_counter() - t0
    save_torch(
        out / policy_file(objective),
        {
            "format": CHECKPOINT_FORMAT,
            "signature": signature(sc),
            "state_dict": agent.state_dict(),
            "hidden_size": agent.hidden_size,
            "prior": agent.prior,
            "driver_speed": getattr(cfg, "driver_speed", "none"),
            "driver_follow": getattr(cfg, "driver_follow", "none"),
            "objective": objective,
            "scenario": sc.to_dict(),
        },
    )
    write_csv(pd.DataFrame(log), out / policy_file(objective, "train_log"))
    out_res = {"agent": agent, "wall_s": wall, "env_steps": env_steps, "log": log}
    if warm is not None:
        out_res["warmup_states"] = len(warm)
    return out_res

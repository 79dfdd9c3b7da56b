"""Stage II: PPO for the shared policy, J(theta) = E[r_micro + eta r_macro] (paper, Alg. 1).

Read top to bottom as CleanRL's ppo_continuous_action: agent, rollout, GAE, update.

* The policy is a Gaussian over the acceleration with a state-independent std; the env
  clips the sample to [a_min, a_max]. One policy drives every hidden vehicle.
* r_macro enters through the policy gradient: each hidden vehicle's reward is
  eta * r_macro,t (shared), with a value baseline, GAE and the clipped surrogate.
* r_micro = sum log pi(u | o) over observed vehicles depends on theta directly, so it is a
  likelihood term of the loss on the observed (o, u) pairs: its gradient is exact. Both
  terms are averaged per vehicle-step, so eta keeps its meaning as the macro weight.
  Advantages are normalised only when there is no likelihood term (macro_only).
* Ablations (``policy.objective``): ``mix`` (the paper), ``micro_only`` (eta = 0:
  behaviour cloning), ``macro_only`` (no likelihood term).
* The env core is the ring's ``RingCore`` or a section's ``SectionCore`` (``make_core``).
  On a section vehicles leave mid-episode and recorded actions can be unknown: steps of
  an inactive vehicle carry no loss (its value target ends there), NaN actions no
  likelihood. Observations are normalised with fixed ring constants on the ring and with
  the mean/std of the bank's initial observations on a section (buffers of the agent, so
  they travel in the checkpoint's state_dict).
"""

from __future__ import annotations

import copy
import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import nn

from macromicro_sumo.checkpoints import save_torch
from macromicro_sumo.data.ring import load_ground_truth, split_runs
from macromicro_sumo.env.observation import OBS_SHIFT_SCALE
from macromicro_sumo.env.ring import EpisodeBank, RingCore, build_bank, generator_completion
from macromicro_sumo.env.rollout import ActionFn, rollout
from macromicro_sumo.env.section import SectionBank, SectionCore, initial_observations
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import file_sha256, prepare_out_dir, write_csv, write_json
from macromicro_sumo.generator.ring_train import load_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.progress import tqdm
from macromicro_sumo.road.physics import OBSERVATION_FEATURES
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.scenario.section import SectionScenario

CHECKPOINT_FORMAT = "macromicro-policy"
# Fixed observation scaling per feature: env.observation.FEATURES (the envs' normalize too).


# --------------------------------------------------------------------------- agent


class Agent(nn.Module):
    def __init__(
        self,
        hidden_size: int = 64,
        init_log_std: float = -1.0,
        observation: str = "paper",
        shift_scale: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """``shift_scale``: the observation normalisation (None: the ring's OBS_SHIFT_SCALE)."""
        super().__init__()
        features = OBSERVATION_FEATURES[observation]
        obs_dim = len(features)
        self.observation = observation
        if shift_scale is None:
            shift = torch.tensor([OBS_SHIFT_SCALE[f][0] for f in features])
            scale = torch.tensor([OBS_SHIFT_SCALE[f][1] for f in features])
        else:
            shift = torch.as_tensor(np.asarray(shift_scale[0]), dtype=torch.float32)
            scale = torch.as_tensor(np.asarray(shift_scale[1]), dtype=torch.float32)
        self.register_buffer("shift", shift)
        self.register_buffer("scale", scale)
        self.actor = nn.Sequential(
            nn.Linear(obs_dim, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, 1),
        )
        self.critic = nn.Sequential(
            nn.Linear(obs_dim + 1, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, 1),
        )
        self.log_std = nn.Parameter(torch.full((1,), float(init_log_std)))
        self.hidden_size = hidden_size

    def dist(self, obs: torch.Tensor) -> torch.distributions.Normal:
        mean = self.actor((obs - self.shift) / self.scale).squeeze(-1)
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean))

    def value(self, obs: torch.Tensor, t_frac: torch.Tensor) -> torch.Tensor:
        x = torch.cat([(obs - self.shift) / self.scale, t_frac[..., None]], dim=-1)
        return self.critic(x).squeeze(-1)


def policy_action(agent, stochastic: bool = True) -> ActionFn:
    def act(core: RingCore, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        with torch.no_grad():
            d = agent.dist(torch.as_tensor(obs[core.hidden], dtype=torch.float32))
        mean, std = d.mean.numpy(), d.stddev.numpy()
        return mean + std * rng.standard_normal(mean.shape) if stochastic else mean

    return act


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


def observation_shift_scale(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-feature mean and std of ``obs`` (V, D); a constant feature gets scale 1."""
    if len(obs) == 0:
        return np.zeros(obs.shape[1]), np.ones(obs.shape[1])
    shift, scale = obs.mean(axis=0), obs.std(axis=0)
    return shift, np.where(scale > 1e-6, scale, 1.0)


def clipped_actions(actions: np.ndarray, a_min: float, a_max: float) -> tuple[np.ndarray, float]:
    """Ground-truth actions clipped to the bounds for the likelihood, and the clipped share."""
    out = np.clip(actions, a_min, a_max)
    return out, float((out != actions).mean()) if actions.size else 0.0


# --------------------------------------------------------------------------- rollout


@dataclass
class Rollout:
    obs: np.ndarray  # (E, H, N, obs_dim)
    actions: np.ndarray  # (E, H, N)
    logp: np.ndarray
    values: np.ndarray
    rewards: np.ndarray  # (E, H)
    hidden: np.ndarray  # (E, N)
    gt_actions: np.ndarray  # (E, H, N) (NaN: unknown)
    r_macro: np.ndarray  # (E, H)
    collisions: int
    sumo_errors: int
    active: np.ndarray  # (E, H, N) bool: the vehicle was on the road at the step (ring: all)
    leader_hidden: np.ndarray  # (E, H, N) bool: the vehicle's leader at the step is hidden


Core = RingCore | SectionCore


def collect(
    agent: Agent,
    core: Core,
    episodes: np.ndarray,
    eta: float,
    horizon: int,
    gen: torch.Generator,
) -> Rollout:
    n = core.n
    section = isinstance(core, SectionCore)
    active = np.ones((len(episodes), horizon, n), dtype=bool)
    e_n = len(episodes)
    leader_hidden = np.zeros((e_n, horizon, n), dtype=bool)
    obs = np.zeros((e_n, horizon, n, core.obs_dim), dtype=np.float32)
    act = np.zeros((e_n, horizon, n), dtype=np.float32)
    logp = np.zeros_like(act)
    val = np.zeros_like(act)
    r_macro = np.zeros((e_n, horizon), dtype=np.float32)
    hidden = core.bank.hidden[episodes]
    collisions = errors = 0
    t_frac = torch.arange(horizon, dtype=torch.float32) / horizon
    for i, ep in enumerate(episodes):
        o = core.reset(int(ep))
        for t in range(horizon):
            if section:
                active[i, t] = core.active
            leader_hidden[i, t] = (core.leader >= 0) & hidden[i][np.maximum(core.leader, 0)]
            ot = torch.as_tensor(o, dtype=torch.float32)
            with torch.no_grad():
                d = agent.dist(ot)
                a = d.mean + d.stddev * torch.randn(d.mean.shape, generator=gen)
                obs[i, t], act[i, t] = o, a.numpy()
                logp[i, t] = d.log_prob(a).numpy()
                val[i, t] = agent.value(ot, t_frac[t].expand(n)).numpy()
            res = core.step(act[i, t][hidden[i]])
            r_macro[i, t] = res.r_macro
            o = res.obs
            if res.collision or res.truncated:
                collisions += res.collision
                errors += bool(res.error)
                obs[i, t + 1 :] = o  # the episode ends here: later steps carry no reward
                leader_hidden[i, t + 1 :] = leader_hidden[i, t]
                if section:
                    active[i, t + 1 :] = False
                break
    return Rollout(
        obs,
        act,
        logp,
        val,
        eta * r_macro,
        hidden,
        core.bank.gt_accel_mps2[episodes][:, :horizon],
        r_macro,
        collisions,
        errors,
        active,
        leader_hidden,
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
    agent: Agent, core: Core, episodes: np.ndarray, horizon: int, sc: Scenario | SectionScenario
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


def mean_logp(agent: Agent, obs: torch.Tensor, actions: torch.Tensor) -> float:
    """Mean log-likelihood of ``actions`` under the agent (NaN without pairs)."""
    if len(obs) == 0:
        return float("nan")
    with torch.no_grad():
        return float(agent.dist(obs).log_prob(actions).mean())


def learning_rate(lr: float, schedule: str, update: int, n_updates: int) -> float:
    """Adam's rate at ``update`` (0-based): constant, or linear decay reaching 0 after the last."""
    return lr * (1.0 - update / n_updates) if schedule == "linear" else lr


def signature(sc: Scenario | SectionScenario) -> dict[str, Any]:
    """What a policy checkpoint must agree on with the scenario that loads it."""
    if isinstance(sc, SectionScenario):
        return {
            "network.kind": "sumo",
            "section.edges": ",".join(sc.section.edges),
            "section.closed": sc.section.closed,
            "bounds.accel_mps2": list(sc.bounds.accel_mps2),
            "simulation.step_length_s": sc.simulation.step_length_s,
            "policy.observation": ",".join(OBSERVATION_FEATURES[sc.policy.observation]),
        }
    return {
        "fleet.n_vehicles": sc.fleet.n_vehicles,
        "network.radius_m": sc.network.radius_m,
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


def load_checkpoint(path: Path, sc: Scenario) -> dict[str, Any]:
    payload = read_checkpoint(path)
    want = signature(sc)
    for key, have in payload["signature"].items():
        if want.get(key) != have:
            raise UserError(
                f"{path}: policy was trained for {key} = {have}, scenario {sc.source} has {want.get(key)}"
            )
    return payload


def resumable_checkpoint(
    path: Path, sc: Scenario, run_key: str, resume: bool | str
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


def load_policy(path: Path | str, sc: Scenario) -> Agent:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: policy checkpoint not found (run `macromicro train-policy`)")
    payload = load_checkpoint(path, sc)
    agent = Agent(payload["hidden_size"], observation=sc.policy.observation)
    agent.load_state_dict(payload["state_dict"])
    agent.eval()
    return agent


def train_policy(
    sc: Scenario | SectionScenario,
    bank: EpisodeBank | SectionBank,
    out: Path,
    objective: str | None = None,
    resume: bool | str = False,
    progress: bool = True,
    updates: int | None = None,
    run_key: str = "",
    init: dict[str, Any] | None = None,
    make_core: Callable[[Any, int], Core] | None = None,
    val_runs: np.ndarray | None = None,
) -> dict[str, Any]:
    """PPO on the env over ``bank``; writes policy.pt, policy_train_log.csv, checkpoints.

    ``make_core(bank, seed)`` builds the env core (default: the ring's ``RingCore``; a
    section passes one that builds its ``SectionCore``). With ``policy.checkpoint_selection
    = "val_micro_logp"``, the episodes of ``val_runs`` are kept out of training and the
    policy returned and saved is the update's with the best validation micro log-likelihood.
    """
    cfg = sc.policy
    objective = objective or cfg.objective
    eta = 0.0 if objective == "micro_only" else sc.policy.eta
    use_micro = objective != "macro_only"
    n_updates = updates or cfg.updates
    ckpt_path = out / f"policy_{objective}_checkpoint.pt"
    if make_core is None:
        make_core = lambda b, seed: RingCore(sc, b, seed=seed)  # noqa: E731
    core = make_core(bank, sc.seed)
    t0 = time.perf_counter()
    env_steps = 0
    try:
        shift_scale = None
        if isinstance(core, SectionCore):
            shift_scale = observation_shift_scale(initial_observations(sc, core.section, bank))
        torch.manual_seed(sc.seed)
        agent = Agent(cfg.hidden_size, cfg.init_log_std, cfg.observation, shift_scale)
        if init is not None:
            agent.load_state_dict(init)
        # macro_only never sees observed actions: choosing its update by them would leak them.
        select = cfg.checkpoint_selection == "val_micro_logp" and objective != "macro_only"
        train_eps, val_eps = split_episodes(bank.run, val_runs if select else None)
        val_obs, val_act = validation_pairs(agent, core, val_eps, cfg.horizon, sc)
        best_val, best_state = -float("inf"), None
        opt = torch.optim.Adam(agent.parameters(), lr=cfg.lr)
        rng = np.random.default_rng([sc.seed, 41])
        gen = torch.Generator().manual_seed(sc.seed)
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
        a_min, a_max = sc.bounds.accel_mps2
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
            ro = collect(agent, core, episodes, eta, cfg.horizon, gen)
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
            if not use_micro and len(b_adv) > 1:
                b_adv = (b_adv - b_adv.mean()) / (b_adv.std() + 1e-8)
            gt, clip_share = clipped_actions(ro.gt_actions[obs_pairs], a_min, a_max)
            micro_pool.append(
                (torch.as_tensor(ro.obs[obs_pairs]), torch.as_tensor(gt, dtype=torch.float32))
            )
            del micro_pool[: -cfg.micro_replay]
            m_obs = torch.cat([o for o, _ in micro_pool])
            m_act = torch.cat([a for _, a in micro_pool])
            n_b, n_m = len(b_obs), len(m_obs)
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
                    opt.zero_grad()
                    loss.backward()
                    nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
                    opt.step()
            micro_all = mean_logp(agent, *micro_pool[-1])
            val_logp = mean_logp(agent, val_obs, val_act)
            if val_logp > best_val:  # NaN (no validation pairs) never is: the last one is kept
                best_val, best_state = val_logp, copy.deepcopy(agent.state_dict())
            row = {
                "update": update + 1,
                "env_steps": (update + 1) * cfg.episodes_per_update * cfg.horizon,
                "r_macro": float(ro.r_macro.mean()),
                "r_micro_per_pair": micro_all,
                "val_micro_logp": val_logp,
                **{k: float(np.mean(v)) if v else float("nan") for k, v in stats.items()},
                "action_std_mps2": float(agent.log_std.detach().exp()),
                "collisions": ro.collisions,
                "sumo_errors": ro.sumo_errors,
                "gt_actions_clipped_share": clip_share,
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
                        "micro_pool": micro_pool,
                        "best_val": best_val,
                        "best_state_dict": best_state,
                    },
                )
    finally:
        core.close()
    if best_state is not None:
        agent.load_state_dict(best_state)
    wall = time.perf_counter() - t0
    save_torch(
        out / (f"policy_{objective}.pt" if objective != "mix" else "policy.pt"),
        {
            "format": CHECKPOINT_FORMAT,
            "signature": signature(sc),
            "state_dict": agent.state_dict(),
            "hidden_size": agent.hidden_size,
            "objective": objective,
            "scenario": sc.to_dict(),
        },
    )
    name = "policy_train_log.csv" if objective == "mix" else f"policy_train_log_{objective}.csv"
    write_csv(pd.DataFrame(log), out / name)
    return {"agent": agent, "wall_s": wall, "env_steps": env_steps, "log": log}


def policy_run_key(sc, data: Path, generator: Path, objective: str) -> str:
    """What a resumable checkpoint must belong to: scenario, ground truth, generator, objective."""
    return hashlib.sha256(
        f"{sc.digest()}|{file_sha256(generator)}|{file_sha256(Path(data) / 'trajectories.csv')}|{objective}".encode()
    ).hexdigest()


def training_bank(sc: Scenario, gt, net, splits: dict[str, np.ndarray]):
    """The ring policy's episodes: train + val runs completed by the generator (scenario seed)."""
    return build_bank(
        sc,
        gt,
        np.concatenate([splits["train"], splits["val"]]),
        generator_completion(net, sc, sc.seed),
        sc.policy.hidden_train,
        sc.seed,
    )


def heldout_speed(sc: Scenario, gt, net, agent, held: np.ndarray) -> pd.DataFrame:
    """Per K: the fleet's mean speed on the held-out runs, policy-driven vs recorded."""
    rows, h = [], sc.policy.horizon
    for k in range(sc.generator.hidden_eval[0], sc.generator.hidden_eval[1] + 1):
        bank = build_bank(sc, gt, held, generator_completion(net, sc, sc.seed + k), k, sc.seed + k)
        core = RingCore(sc, bank, seed=sc.seed)
        try:
            ro = rollout(core, policy_action(agent), h, sc.seed + k)
        finally:
            core.close()
        v, v_gt = np.nanmean(ro.speed_mps), bank.replay_speed_mps[:, 1 : h + 1].mean()
        rows.append(
            {
                "K": k,
                "mean_speed_mps": v,
                "gt_mean_speed_mps": v_gt,
                "abs_error_mps": abs(v - v_gt),
                "collisions": ro.collisions,
                "episodes": len(bank),
            }
        )
    return pd.DataFrame(rows)


def run_train_policy(
    sc: Scenario,
    data: Path,
    generator: Path,
    out: Path,
    resume: bool | str = False,
    command: str = "",
    progress: bool = True,
    objective: str | None = None,
) -> dict[str, Any]:
    """CLI stage: episodes from train+val runs completed by the generator, PPO, held-out check."""
    objective = objective or sc.policy.objective

    net = load_generator(generator, sc)
    gt = load_ground_truth(data, sc)
    out, run_key, splits = open_policy_stage(sc, gt.runs, data, generator, out, objective, resume)
    bank = training_bank(sc, gt, net, splits)
    res = train_policy(
        sc,
        bank,
        out,
        objective=objective,
        resume=resume,
        progress=progress,
        run_key=run_key,
        val_runs=splits["val"],
    )
    # Held-out check of the target: fleet mean speed vs ground truth per K.
    align = heldout_speed(sc, gt, net, res["agent"], splits["held_out"])
    suffix = "" if objective == "mix" else f"_{objective}"
    write_csv(align, out / f"policy_heldout_speed{suffix}.csv")
    manifest = write_policy_manifest(sc, command, objective, res, data, generator, out)
    return {"alignment": align, **manifest}


def open_policy_stage(
    sc, runs: np.ndarray, data: Path, generator: Path, out: Path, objective: str, resume: bool | str
) -> tuple[Path, str, dict[str, np.ndarray]]:
    """The head of a policy stage (ring or section): the output folder, the run key, and the
    run split. Checks a checkpoint to resume before anything is overwritten."""
    out = prepare_out_dir(out)
    run_key = policy_run_key(sc, data, generator, objective)
    resumable_checkpoint(out / f"policy_{objective}_checkpoint.pt", sc, run_key, resume)
    torch.set_num_threads(1)
    return out, run_key, split_runs(runs, sc.generator.held_out_fraction, sc.seed)


def write_policy_manifest(
    sc, command: str, objective: str, res: dict, data: Path, generator: Path, out: Path, **extra
) -> dict[str, Any]:
    """``policy_manifest[_objective].json`` of a policy stage (ring or section); returned.
    Written last: the pipeline takes a stage with its manifest as done."""
    suffix = "" if objective == "mix" else f"_{objective}"
    manifest = build_manifest(sc, command, stage=f"train-policy{suffix}")
    manifest.update(
        timings_s={"train_policy": round(res["wall_s"], 3)},
        env_steps=res["env_steps"],
        **extra,
        ground_truth=str(data),
        generator=str(generator),
    )
    write_json(manifest, out / f"policy_manifest{suffix}.json")
    return manifest

"""PPO's rollouts of demand episodes (``env.demand``): one trajectory per driven vehicle.

A demand episode lasts ``policy.demand_horizon_s`` and its vehicles come and go, so its
batch is flat (one row per driven vehicle-step) and GAE runs along each vehicle's own
steps:

* every step's reward is eta * r_macro of the scene (shared, as in snapshot episodes);
* a vehicle that leaves the section, or is still driving when the window ends, is
  truncated: its return is bootstrapped with its last value, so that leaving early or late
  is neither rewarded nor punished (a terminal there, with r_macro > 0, would pay a vehicle
  for staying on the section, that is for driving slowly);
* a vehicle that collides is terminal (no future reward) and gets
  ``-policy.collision_penalty`` on that step;
* the batch's advantages are standardised and weighted by eta (``collect_demand``);
* with ``policy.driver_speed``, each driver observes its own limits (``agent_quantiles``,
  ``env.demand.DemandCore.set_driver_speeds``), as the deployed policy's drivers do.

The critic's time input is ``DEMAND_T_FRAC`` for every demand step: these episodes have no
horizon to count down, unlike snapshot episodes (t / H in [0, 1)).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import torch

from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.prior import prior_buffer

DEMAND_T_FRAC = -1.0


@dataclass
class DemandBatch:
    """Flat PPO rows of demand episodes, with what the training log reports."""

    obs: np.ndarray  # (B, obs_dim)
    actions: np.ndarray  # (B,)
    logp: np.ndarray
    advantages: np.ndarray
    returns: np.ndarray
    r_macro: float  # mean over the episodes' steps
    collided: int  # driven vehicles removed after a collision
    collisions: int  # SUMO's count, every vehicle
    teleports: int
    vehicle_steps: int


@dataclass
class _Track:
    obs: list
    act: list
    logp: list
    value: list
    reward: list
    terminal: bool = False


def vehicle_gae(
    rewards: np.ndarray, values: np.ndarray, terminal: bool, gamma: float, lam: float
) -> tuple[np.ndarray, np.ndarray]:
    """GAE along one vehicle's steps; after the last step the value is 0 if ``terminal``,
    else the last value (a truncation bootstrapped with the vehicle's own estimate)."""
    adv = np.zeros_like(rewards)
    last = 0.0
    after = 0.0 if terminal else float(values[-1])
    for t in reversed(range(len(rewards))):
        next_v = values[t + 1] if t + 1 < len(rewards) else after
        delta = rewards[t] + gamma * next_v - values[t]
        last = delta + gamma * lam * last
        adv[t] = last
    return adv, adv + values


def agent_quantiles(agent: Agent, buffer: str) -> np.ndarray | None:
    """The drivers' quantiles the agent carries in ``buffer`` ("driver_speed": desired-speed
    ratios, ``policy.driver_speed``; "driver_tau": taus, ``policy.driver_follow``; None:
    none), in float64 as the deployment hands them to ``DriverSpeeds`` / ``DriverTaus``
    (``deploy.policy_batch``), so that a vehicle gets the same factor and tau in both."""
    q = getattr(agent, buffer, None)
    return None if q is None else q.double().numpy()


def set_driver_draws(core: DemandCore, agent: Agent) -> None:
    """The demand core's drivers draw their desired-speed factors and taus from the agent's
    quantiles (``agent_quantiles``), as the deployment's do."""
    core.set_driver_speeds(agent_quantiles(agent, "driver_speed"))
    handover = prior_buffer(agent) if agent.prior == "krauss" else None  # as policy_batch
    core.set_driver_taus(agent_quantiles(agent, "driver_tau"), handover)


def collect_demand(
    agent: Agent,
    core: DemandCore,
    windows: list[tuple[int, float]],
    eta: float,
    penalty: float,
    gamma: float,
    lam: float,
    gen: torch.Generator,
) -> DemandBatch:
    """Drive the demand episodes ``windows`` (run, t0) with the stochastic policy."""
    tracks: list[_Track] = []
    rewards, collided, collisions, teleports, steps = [], 0, 0, 0, 0
    t_frac = torch.tensor(DEMAND_T_FRAC)
    set_driver_draws(core, agent)
    for run, t0 in windows:
        c0, tp0 = core.counts["collisions"], core.counts["teleports"]
        core.reset(run, t0)
        live: dict[str, _Track] = {}
        for _ in range(core.horizon):
            vids, o = core.observe()
            if vids:
                ot = torch.as_tensor(o, dtype=torch.float32)
                with torch.no_grad():
                    d = agent.dist(ot)
                    a = d.mean + d.stddev * torch.randn(d.mean.shape, generator=gen)
                    lp = d.log_prob(a).numpy()
                    v = agent.value(ot, t_frac.expand(len(vids))).numpy()
                a = a.numpy()
                for i, vid in enumerate(vids):
                    tr = live.get(vid)
                    if tr is None:
                        tr = live[vid] = _Track([], [], [], [], [])
                        tracks.append(tr)
                    tr.obs.append(o[i])
                    tr.act.append(a[i])
                    tr.logp.append(lp[i])
                    tr.value.append(v[i])
            else:
                a = np.zeros(0)
            res = core.step(a)
            steps += len(vids)
            rewards.append(res.r_macro)
            for vid in vids:
                live[vid].reward.append(eta * res.r_macro)
            for vid in res.collided:
                tr = live.pop(vid)
                tr.reward[-1] -= penalty
                tr.terminal = True
                collided += 1
            for vid in res.left:
                live.pop(vid, None)
        collisions += core.counts["collisions"] - c0
        teleports += core.counts["teleports"] - tp0
    parts = []
    for tr in tracks:
        val = np.asarray(tr.value, dtype=np.float32)
        adv, ret = vehicle_gae(
            np.asarray(tr.reward, dtype=np.float32), val, tr.terminal, gamma, lam
        )
        parts.append((np.asarray(tr.obs), np.asarray(tr.act), np.asarray(tr.logp), adv, ret))
    if parts:
        cols = [np.concatenate(x).astype(np.float32) for x in zip(*parts, strict=True)]
        # Standardised, then weighted by eta: a vehicle's return sums ~1 / (1 - gamma)
        # shared rewards, so raw advantages of a 120 s window are ~10x a snapshot
        # episode's and, before the critic has learned them, the same sign for most
        # actions: measured on Bremen (40 updates), the policy drifted and its demand
        # episodes' collisions rose from ~25 to ~75 per episode.
        adv = cols[3]
        if len(adv) > 1:
            cols[3] = (eta * (adv - adv.mean()) / (adv.std() + 1e-8)).astype(np.float32)
    else:
        z = np.zeros(0, dtype=np.float32)
        cols = [np.zeros((0, core.obs_dim), dtype=np.float32), z, z, z, z]
    return DemandBatch(
        *cols,
        float(np.mean(rewards)) if rewards else float("nan"),
        collided,
        collisions,
        teleports,
        steps,
    )


def prior_step(agent: Agent, core: DemandCore) -> np.ndarray | None:
    """One step of ``core`` with its population driven by ``agent``'s prior alone; the
    observations it drove on (N, obs_dim), None where no vehicle was driven."""
    vids, o = core.observe()
    a = np.zeros(0)
    if vids:
        with torch.no_grad():
            a = agent.prior_accel(torch.as_tensor(o, dtype=torch.float32)).numpy()
    core.step(a)
    return o if vids else None


def warmup_states(agent: Agent, core: DemandCore, warmup_s: float) -> np.ndarray:
    """Observations (N, obs_dim) of the population through the warm-up of each of
    ``core.runs`` (from SUMO's first step to ``warmup_s``), driven by the agent's prior
    alone: the start every deployment drives into (a ring's fleet departing standing), which
    no snapshot episode shows (they start after the warm-up). ``policy.residual``'s
    warm-up anchors hold the residual at 0 where these lie off the pairs. With
    ``policy.driver_speed`` each driver observes its own limits (``agent_quantiles``), as
    in ``collect_demand`` and the deployment."""
    dt = core.dt
    out = []
    set_driver_draws(core, agent)
    for run in core.runs:
        core.reset(int(run), dt)
        for _ in range(int(round(warmup_s / dt)) - 1):
            o = prior_step(agent, core)
            if o is not None:
                out.append(o)
    if not out:
        return np.zeros((0, core.obs_dim), dtype=np.float32)
    return np.concatenate(out).astype(np.float32)


def prior_warmup_states(
    sc,
    prior_params: Mapping[str, float],
    make_demand: Callable[[], DemandCore],
    driver_speed: np.ndarray | None = None,
    driver_tau: np.ndarray | None = None,
) -> np.ndarray:
    """``warmup_states`` of the training runs' demand (``make_demand``) under the fitted
    prior alone (``policy.prior``, ``prior_params``), its drivers' desired-speed factors
    from ``driver_speed`` (the trained agent's quantiles, ``policy.driver_speed``); a
    demand core of its own (each driver's own tau from ``driver_tau``,
    ``policy.driver_follow``), closed before the snapshot env starts, so that env runs as it
    did without it."""
    agent = Agent(
        observation=sc.policy.observation,
        prior=sc.policy.prior,
        prior_params=prior_params,
        driver_speed=driver_speed,
        driver_tau=driver_tau,
    )
    core = make_demand()
    try:
        return warmup_states(agent, core, sc.simulation.warmup_s)
    finally:
        core.close()


def join_demand(batch: tuple[torch.Tensor, ...], db: DemandBatch) -> tuple[torch.Tensor, ...]:
    """The snapshot episodes' PPO rows (obs, action, logp, advantage, return, t_frac)
    followed by the demand episodes'."""
    extra = (
        db.obs,
        db.actions,
        db.logp,
        db.advantages,
        db.returns,
        np.full(len(db.actions), DEMAND_T_FRAC, dtype=np.float32),
    )
    return tuple(
        torch.cat([b, torch.as_tensor(x, dtype=b.dtype)]) for b, x in zip(batch, extra, strict=True)
    )


def demand_log(db: DemandBatch | None) -> dict[str, float]:
    """The training log's demand columns (NaN without demand episodes)."""
    if db is None:
        return {}
    return {
        "demand_r_macro": db.r_macro,
        "demand_vehicle_steps": db.vehicle_steps,
        "demand_collided": db.collided,
        "demand_collisions": db.collisions,
        "demand_teleports": db.teleports,
    }

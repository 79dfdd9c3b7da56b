"""PPO's rollouts of snapshot episodes: ``collect`` on a ``SectionCore``, one episode after
the other, and ``collect_batched`` on a ``BatchedSectionCore``, B episodes per SUMO step.

``collect_batched`` returns the ``Rollout`` that ``collect`` returns over the same episodes
with a generator in the same state, to the bit (tests/policy/test_batched_collect.py): the
batched core gives each scene SectionCore's trajectory, the policy's forward pass runs per
episode (a larger batch may round differently), and the action noise is drawn in
``collect``'s order. ``collect`` draws one (N,) normal per step of each episode in turn,
fewer for an episode that ends early, so a chunk of episodes runs on noise drawn as if all
ran H steps and, where one ended early, the episodes after it run again on the noise they
would have had. ``policy.ppo.train_policy`` uses it where the section is one the batched
core takes (the ring): docs/design.md, "Env speed (stop 26)".

With ``policy.driver_follow`` the bank holds each slot's tau (``SectionBank.driver_tau``):
both append it to every observation as a trailing column (``own_taus``), which the agent's
prior reads and PPO's stored observations keep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from macromicro_sumo.env.batched import BatchedSectionCore
from macromicro_sumo.env.driver_tau import with_tau
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.policy.agent import Agent


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
    active: np.ndarray  # (E, H, N) bool: the vehicle was on the road at the step
    leader_hidden: np.ndarray  # (E, H, N) bool: the vehicle's leader at the step is hidden


def own_taus(obs: np.ndarray, taus: np.ndarray | None, episodes) -> np.ndarray:
    """``obs`` (..., N, D) of ``episodes`` (an episode, or one per scene) with each slot's
    tau (``taus``: the bank's ``driver_tau``) as a trailing column; as it is without."""
    return obs if taus is None else with_tau(obs, taus[episodes])


def collect(
    agent: Agent,
    core: SectionCore,
    episodes: np.ndarray,
    eta: float,
    horizon: int,
    gen: torch.Generator,
) -> Rollout:
    n = core.n
    active = np.ones((len(episodes), horizon, n), dtype=bool)
    e_n = len(episodes)
    leader_hidden = np.zeros((e_n, horizon, n), dtype=bool)
    taus = core.bank.driver_tau
    dim = core.obs_dim + (taus is not None)
    obs = np.zeros((e_n, horizon, n, dim), dtype=np.float32)
    act = np.zeros((e_n, horizon, n), dtype=np.float32)
    logp = np.zeros_like(act)
    val = np.zeros_like(act)
    r_macro = np.zeros((e_n, horizon), dtype=np.float32)
    hidden = core.bank.hidden[episodes]
    collisions = errors = 0
    t_frac = torch.arange(horizon, dtype=torch.float32) / horizon
    for i, ep in enumerate(episodes):
        o = own_taus(core.reset(int(ep)), taus, int(ep))
        for t in range(horizon):
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
            o = own_taus(res.obs, taus, int(ep))
            if res.collision or res.truncated:
                collisions += res.collision
                errors += bool(res.error)
                obs[i, t + 1 :] = o  # the episode ends here: later steps carry no reward
                leader_hidden[i, t + 1 :] = leader_hidden[i, t]
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


def collect_batched(
    agent: Agent,
    core: BatchedSectionCore,
    episodes: np.ndarray,
    eta: float,
    horizon: int,
    gen: torch.Generator,
) -> Rollout:
    """``collect``'s rollout of ``episodes``, ``core.b`` of them per SUMO step."""
    n, e_n = core.n, len(episodes)
    dim = core.obs_dim + (core.bank.driver_tau is not None)
    ro = Rollout(
        np.zeros((e_n, horizon, n, dim), dtype=np.float32),
        np.zeros((e_n, horizon, n), dtype=np.float32),
        np.zeros((e_n, horizon, n), dtype=np.float32),
        np.zeros((e_n, horizon, n), dtype=np.float32),
        np.zeros((e_n, horizon), dtype=np.float32),
        core.bank.hidden[episodes],
        core.bank.gt_accel_mps2[episodes][:, :horizon],
        np.zeros((e_n, horizon), dtype=np.float32),
        0,
        0,
        np.ones((e_n, horizon, n), dtype=bool),
        np.zeros((e_n, horizon, n), dtype=bool),
    )
    length = np.full(e_n, horizon)
    collided = np.zeros(e_n, dtype=bool)
    failed = np.zeros(e_n, dtype=bool)
    p = 0
    while p < e_n:
        idx = np.arange(p, min(p + core.b, e_n))
        state = gen.get_state()
        noise = [[torch.randn((n,), generator=gen) for _ in range(horizon)] for _ in idx]
        _run_chunk(agent, core, episodes, idx, noise, ro, length, collided, failed)
        # Keep the chunk up to its first episode that ended early; the generator then
        # stands where collect's stands after those episodes.
        short = np.flatnonzero(length[idx] < horizon)
        keep = idx if short.size == 0 else idx[: short[0] + 1]
        gen.set_state(state)
        for _ in range(int(length[keep].sum())):
            torch.randn((n,), generator=gen)
        p = int(keep[-1]) + 1
    ro.r_macro[:] = ro.rewards
    ro.rewards[:] = eta * ro.r_macro
    ro.collisions, ro.sumo_errors = int(collided.sum()), int(failed.sum())
    return ro


def _run_chunk(
    agent: Agent,
    core: BatchedSectionCore,
    episodes: np.ndarray,
    idx: np.ndarray,
    noise: list[list[torch.Tensor]],
    ro: Rollout,
    length: np.ndarray,
    collided: np.ndarray,
    failed: np.ndarray,
) -> None:
    """Episodes ``idx`` (at most B) side by side: ``collect``'s loop body per scene;
    ``ro.rewards`` gets r_macro (scaled by the caller)."""
    m, n, horizon = len(idx), core.n, ro.actions.shape[1]
    # A chunk run again (after an early end before it) starts clean.
    length[idx], collided[idx], failed[idx] = horizon, False, False
    ro.active[idx], ro.leader_hidden[idx] = True, False
    # Every scene restarts (the spare ones of a last, short chunk on its first episode,
    # not recorded): a full reset also takes libsumo back from another core.
    reset = np.full(core.b, episodes[idx[0]])
    reset[:m] = episodes[idx]
    taus = core.bank.driver_tau
    o = own_taus(core.step(np.zeros((core.b, n), dtype=np.float32), reset).obs, taus, reset)
    live = np.ones(m, dtype=bool)
    t_frac = torch.arange(horizon, dtype=torch.float32) / horizon
    accel = np.zeros((core.b, n), dtype=np.float32)  # float32 as collect's: same clipping
    for t in range(horizon):
        for j in np.flatnonzero(live):
            i = idx[j]
            ro.active[i, t] = core.active[j]
            lead = core.leader[j]
            ro.leader_hidden[i, t] = (lead >= 0) & ro.hidden[i][np.maximum(lead, 0)]
            ot = torch.as_tensor(o[j], dtype=torch.float32)
            with torch.no_grad():
                d = agent.dist(ot)
                a = d.mean + d.stddev * noise[j][t]
                ro.obs[i, t], ro.actions[i, t] = o[j], a.numpy()
                ro.logp[i, t] = d.log_prob(a).numpy()
                ro.values[i, t] = agent.value(ot, t_frac[t].expand(n)).numpy()
        accel[:m] = ro.actions[idx, t]
        res = core.step(accel)
        res_obs = own_taus(res.obs, taus, reset)
        for j in np.flatnonzero(live):
            i = idx[j]
            ro.rewards[i, t] = res.r_macro[j]
            if res.collision[j] or res.truncated[j]:
                collided[i] = res.collision[j]
                failed[i] = bool(res.errors[j])
                ro.obs[i, t + 1 :] = res_obs[j]  # the episode ends: later steps carry no reward
                ro.leader_hidden[i, t + 1 :] = ro.leader_hidden[i, t]
                ro.active[i, t + 1 :] = False
                length[i] = t + 1
                live[j] = False
        o = res_obs

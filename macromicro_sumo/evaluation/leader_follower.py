"""Leader-follower tests of a car-following policy (the paper's Fig. 3): the road-free part.

Two vehicles under one uniform speed limit: the leader replays a prescribed speed profile
(``accelerate``: 11 -> 13 m/s, ``decelerate``: 13 -> 11 m/s, a smooth ramp between two
holds), the follower starts 126 m (front to front) behind it at the same speed and is driven
by a *follower function* ``fn(obs, rng) -> accel [m/s^2]`` of its observation
o = [v, v_limit, spacing, v - v_leader]. The ground-truth follower is IDM with given
parameters (deterministic); learned policies sample their Gaussian.

Those figures are the paper's ring's (R = 100 m, N = 5, limits up to 14 m/s): 126 m is its
mean spacing L / N and 11-13 m/s lie below its limit. ``LeaderProfile.moved`` moves the
test to another road: speeds scaled by its limit over 14 m/s, the start spacing by its mean
spacing over the paper's 125.7 m; the paper's ring keeps them exactly. Unscaled, a 230 m
ring with 22 vehicles and limits up to 10 m/s put the follower at a spacing its fleet never
drives, behind a leader faster than its desired speed: the leader came round and ran into it.

The trials themselves (``run_tests``: every follower, the IDM reference, the traces and
the summary) take any core with ``reset`` / ``step``: the section's ``SectionCore`` in
``leader_follower_section`` (open and closed sections, the paper's ring among them).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
import pandas as pd

from macromicro_sumo.env.observation import StepResult
from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.physics import idm_accel

SCENARIOS = ("accelerate", "decelerate")
IDM_METHOD = "IDM"
FOLLOWER, LEADER = 0, 1  # vehicle indices in the two-vehicle bank
IDM_KEYS = ("accel_mps2", "decel_mps2", "tau_s", "min_gap_m", "speed_factor", "delta")
# The ring that ``LeaderProfile``'s figures are stated for: the paper's (R = 100 m, N = 5,
# limits 12-14 m/s); its mean spacing L / N is the 126 m start.
PAPER_MEAN_SPACING_M = 2.0 * math.pi * 100.0 / 5
PAPER_SPEED_LIMIT_MPS = 14.0

Follower = Callable[[np.ndarray, np.random.Generator], float]
"""Acceleration [m/s^2] from one observation [v, v_limit, spacing, v - v_leader] (4,)."""


@dataclass(frozen=True)
class LeaderProfile:
    """The leader's prescribed speed profile and the start of a leader-follower test.

    Speeds, ramp and spacing are stated for the paper's ring; a test on another road runs
    ``moved(...)`` of them (the same values on the paper's ring).
    """

    low_speed_mps: float = 11.0
    """Speed before an acceleration ramp / after a deceleration ramp [m/s]."""
    high_speed_mps: float = 13.0
    """Speed after an acceleration ramp / before a deceleration ramp [m/s]."""
    ramp_mps2: float = 0.2
    """Magnitude of the leader's acceleration during the ramp [m/s^2]."""
    hold_s: float = 20.0
    """Time the first speed is held before the ramp starts [s]."""
    duration_s: float = 60.0
    """Length of a test [s]; a multiple of the scenario's step length."""
    spacing_m: float = 126.0
    """Initial front-to-front distance from the follower to the leader [m]."""

    def moved(self, speed_limit_mps: float, mean_spacing_m: float) -> LeaderProfile:
        """This test on a road of limit ``speed_limit_mps`` whose traffic keeps a mean
        front-to-front spacing ``mean_spacing_m``: speeds and ramp x limit / 14 m/s, the
        start spacing x mean spacing / 125.7 m (the paper ring's L / N)."""
        v = speed_limit_mps / PAPER_SPEED_LIMIT_MPS
        d = mean_spacing_m / PAPER_MEAN_SPACING_M
        return replace(
            self,
            low_speed_mps=self.low_speed_mps * v,
            high_speed_mps=self.high_speed_mps * v,
            ramp_mps2=self.ramp_mps2 * v,
            spacing_m=self.spacing_m * d,
        )

    def horizon(self, dt_s: float) -> int:
        """Steps of ``dt_s`` in a test."""
        h = round(self.duration_s / dt_s)
        if h < 1 or abs(h * dt_s - self.duration_s) > 1e-9 * self.duration_s:
            raise UserError(
                f"leader-follower duration_s = {self.duration_s:g} is not a multiple of the "
                f"step length {dt_s:g} s"
            )
        return h


def leader_speeds(scenario: str, profile: LeaderProfile, dt_s: float) -> np.ndarray:
    """The leader's speed [m/s] at t = 0, dt, ..., duration, shape (H + 1,)."""
    if scenario not in SCENARIOS:
        raise UserError(f"leader-follower scenario {scenario!r}; accepted: {', '.join(SCENARIOS)}")
    if not 0.0 <= profile.low_speed_mps <= profile.high_speed_mps or profile.ramp_mps2 <= 0:
        raise UserError(
            "leader profile needs 0 <= low_speed_mps <= high_speed_mps and ramp_mps2 > 0"
        )
    t = np.arange(profile.horizon(dt_s) + 1) * dt_s
    span = profile.high_speed_mps - profile.low_speed_mps
    ramp = np.clip((t - profile.hold_s) * profile.ramp_mps2, 0.0, span)
    if scenario == "accelerate":
        return profile.low_speed_mps + ramp
    return profile.high_speed_mps - ramp


# --------------------------------------------------------------------------- followers


def mean_idm_params(sc) -> dict[str, float]:
    """IDM parameters at the middle of the scenario's fleet ranges (the 'average driver')."""
    f = sc.fleet
    mid = {k: float(np.mean(getattr(f, k))) for k in IDM_KEYS if k != "delta"}
    return {**mid, "delta": float(f.delta)}


def idm_follower(params: Mapping[str, float], vehicle_length_m: float) -> Follower:
    """The ground-truth follower: IDM with ``params`` (keys ``IDM_KEYS``), deterministic.

    Desired speed = speed_factor x the observed limit; gap = spacing - vehicle length.
    """
    missing = [k for k in IDM_KEYS if k not in params]
    if missing:
        raise UserError(f"IDM parameters miss {', '.join(missing)}; needed: {', '.join(IDM_KEYS)}")
    p = {k: float(params[k]) for k in IDM_KEYS}

    def fn(obs: np.ndarray, rng: np.random.Generator) -> float:
        v, limit, spacing, dv = obs[:4]
        return float(
            idm_accel(
                v,
                spacing - vehicle_length_m,
                dv,
                p["speed_factor"] * limit,
                p["tau_s"],
                p["accel_mps2"],
                p["decel_mps2"],
                p["min_gap_m"],
                p["delta"],
            )
        )

    return fn


def policy_follower(agent, stochastic: bool = True) -> Follower:
    """A follower that samples the agent's Gaussian (``stochastic``) or takes its mean.

    The noise comes from the trial's numpy generator, so a seed fixes the trace.
    """
    import torch

    def fn(obs: np.ndarray, rng: np.random.Generator) -> float:
        with torch.no_grad():
            d = agent.dist(torch.as_tensor(np.asarray(obs, dtype=np.float32)[None]))
        a = float(d.mean[0])
        if stochastic:
            a += float(d.stddev[0]) * float(rng.standard_normal())
        return a

    return fn


# --------------------------------------------------------------------------- runs


@dataclass(frozen=True)
class Trace:
    """One trial: speeds and gap at t = 0, dt, ... until the end or a collision."""

    time_s: np.ndarray
    leader_speed_mps: np.ndarray
    follower_speed_mps: np.ndarray
    gap_m: np.ndarray  # bumper to bumper, follower to leader
    collision: bool


class Core(Protocol):
    """What the trials need of an env core (``SectionCore``)."""

    dt: float
    leader: np.ndarray  # leader slot of every vehicle
    bank: SectionBank

    def reset(self, episode: int) -> np.ndarray: ...
    def step(self, accel_hidden: np.ndarray) -> StepResult: ...


def run_trial(
    core: Core,
    episode: int,
    follower: Follower,
    rng: np.random.Generator,
    vehicle_length_m: float,
    leader_speed_mps: np.ndarray | None = None,
    after_reset: Callable[[Core], None] | None = None,
) -> Trace:
    """Drive the follower of ``episode`` through the whole test; stops at a collision.

    ``leader_speed_mps`` (H + 1,): the leader is a hidden vehicle too (the section's core,
    where a replayed vehicle follows its recorded positions) and is commanded the profile's
    next speed every step; None: the bank replays it. ``after_reset(core)`` runs
    after each reset (the section's: no lane changes).
    """
    obs = core.reset(episode)
    if after_reset is not None:
        after_reset(core)
    h = core.bank.replay_speed_mps.shape[1] - 1
    rows = [(obs[LEADER, 0], obs[FOLLOWER, 0], obs[FOLLOWER, 2] - vehicle_length_m)]
    collision = False
    for t in range(h):
        a = follower(obs[FOLLOWER], rng)
        if leader_speed_mps is None:
            res = core.step(np.array([a]))
        else:  # v' = v + a dt = the profile's next speed (its ramp is within the bounds)
            a_lead = (leader_speed_mps[t + 1] - obs[LEADER, 0]) / core.dt
            res = core.step(np.array([a, a_lead]))
        if res.truncated:
            raise UserError(f"leader-follower test stopped by SUMO: {res.error}")
        obs = res.obs
        gap = obs[FOLLOWER, 2] - vehicle_length_m
        rows.append((obs[LEADER, 0], obs[FOLLOWER, 0], gap))
        if res.collision or gap < 0:
            collision = True
            break
        if core.leader[FOLLOWER] != LEADER:  # a lane change, a red light: no test any more
            ahead = "a standing obstacle" if core.leader[FOLLOWER] < -1 else "no vehicle"
            raise UserError(
                f"leader-follower test: the follower lost its leader at t = "
                f"{(t + 1) * core.dt:g} s (it sees {ahead} ahead)"
            )
    lead, foll, gap = (np.array(c) for c in zip(*rows, strict=True))
    return Trace(np.arange(len(rows)) * core.dt, lead, foll, gap, collision)


def rmse_vs_reference(speed_mps: np.ndarray, reference_mps: np.ndarray) -> float:
    """RMSE [m/s] of a follower trace against the reference over the simulated steps.

    Both start at t = 0 with the same speed, so the first sample is left out; where a
    collision cut either short, they are compared over the steps both have.
    """
    n = min(len(speed_mps), len(reference_mps))
    if n < 2:
        return float("nan")
    return float(np.sqrt(np.mean((speed_mps[1:n] - reference_mps[1:n]) ** 2)))


def check_followers(followers: Mapping[str, Follower], n_trials: int) -> None:
    if IDM_METHOD in followers:
        raise UserError(f"follower name {IDM_METHOD!r} is reserved for the IDM reference")
    if n_trials < 1:
        raise UserError(f"n_trials = {n_trials}; accepted >= 1")


def run_tests(
    core: Core,
    followers: Mapping[str, Follower],
    reference: Follower,
    n_trials: int,
    seed: int,
    vehicle_length_m: float,
    leader_speeds_mps: np.ndarray | None = None,
    after_reset: Callable[[Core], None] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Every scenario of ``SCENARIOS`` (episode i of ``core``'s bank): one trial of the
    ``reference`` follower and ``n_trials`` of every follower; the road's part is the core.

    Trial t of every method in a scenario draws from the generator seeded
    ``[seed, scenario index, t]`` (common random numbers across methods).
    ``leader_speeds_mps`` (E, H + 1): the leader's commanded profile per episode (see
    ``run_trial``). Returns ``(traces, summary)``: traces has one row per (scenario, method,
    trial, step) with the columns of ``leader_follower.csv``; summary one row per trial with
    the RMSE against the reference, the smallest gap and whether the follower collided.
    Where a collision ended the reference before a trial, ``idm_follower_speed_mps`` is NaN
    for the trial's later steps.
    """
    check_followers(followers, n_trials)
    frames, summary = [], []
    for ep, scenario in enumerate(SCENARIOS):
        lead = None if leader_speeds_mps is None else leader_speeds_mps[ep]

        def trial(fn: Follower, rng: np.random.Generator, ep: int = ep, lead=lead) -> Trace:
            return run_trial(core, ep, fn, rng, vehicle_length_m, lead, after_reset)

        ref = trial(reference, np.random.default_rng([seed, ep, 0]))
        runs = [(IDM_METHOD, 0, ref)]
        for method, fn in followers.items():
            for t in range(n_trials):
                runs.append((method, t, trial(fn, np.random.default_rng([seed, ep, t]))))
        for method, t, tr in runs:
            n = len(tr.time_s)
            # A collision ends a trace: the reference may be shorter than this trial.
            ref_speed = np.full(n, np.nan)
            m = min(n, len(ref.follower_speed_mps))
            ref_speed[:m] = ref.follower_speed_mps[:m]
            frames.append(
                pd.DataFrame(
                    {
                        "scenario": scenario,
                        "method": method,
                        "trial": t,
                        "time_s": tr.time_s,
                        "leader_speed_mps": tr.leader_speed_mps,
                        "follower_speed_mps": tr.follower_speed_mps,
                        "idm_follower_speed_mps": ref_speed,
                        "gap_m": tr.gap_m,
                    }
                )
            )
            summary.append(
                {
                    "scenario": scenario,
                    "method": method,
                    "trial": t,
                    "rmse_vs_idm_mps": rmse_vs_reference(
                        tr.follower_speed_mps, ref.follower_speed_mps
                    ),
                    "min_gap_m": float(tr.gap_m.min()),
                    "collision": tr.collision,
                }
            )
    return pd.concat(frames, ignore_index=True), pd.DataFrame(summary)


def method_summary(summary: pd.DataFrame) -> pd.DataFrame:
    """Per (scenario, method): mean and max RMSE against IDM, smallest gap, collisions."""
    g = summary.groupby(["scenario", "method"], sort=False)
    return g.agg(
        trials=("trial", "size"),
        mean_rmse_vs_idm_mps=("rmse_vs_idm_mps", "mean"),
        max_rmse_vs_idm_mps=("rmse_vs_idm_mps", "max"),
        min_gap_m=("min_gap_m", "min"),
        collisions=("collision", "sum"),
    ).reset_index()

"""The learned policy as the deployment drives it: its mean action for every driven
vehicle in one numpy call a step (``policy_batch``), and what the drivers read of it.

With ``policy.driver_follow`` (the agent's ``driver_tau`` buffer) each driven vehicle
observes its own tau as a trailing column (``deploy.observe.observe_rows`` with the
run's ``env.driver_tau.DriverTaus``, which ``policy_batch`` hands the drivers as
``act.driver_taus``): the actor reads the first D columns, the Krauss prior its tau from
the last (``evaluation.driver_follow.krauss_accel_per_driver``), as ``Agent.mean_action``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from functools import partial

import numpy as np
import torch

from macromicro_sumo.deploy.population import ActionBatch
from macromicro_sumo.env.driver_speed import DriverSpeeds
from macromicro_sumo.env.driver_tau import DriverTaus
from macromicro_sumo.evaluation.idm_fit import (
    GippsParams,
    IdmParams,
    gipps_policy_accel,
    idm_policy_accel,
)
from macromicro_sumo.evaluation.krauss_fit import KraussParams, krauss_policy_accel
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.prior import EMERGENCY_DECEL_MPS2, prior_buffer

try:  # road/kernels.c, where setup.py built it (``krauss_batch``)
    from macromicro_sumo.road import kernels
except ImportError:  # not built: numpy's form, the same values
    kernels = None

# Rows per matrix product of the actor's numpy forward pass: larger products start
# OpenBLAS's threads, which on a loaded 2-core machine cost 1.8 ms at 500 rows instead of
# 0.3 ms (scripts/bench_deploy.py's sizes).
ACTOR_ROWS = 128
# ``policy_batch``'s actor_dtype: float64 (its argument's default, Agent.mean_action's values)
# or float32 (the deployment's, ``deploy.actor_dtype``'s default: the dtype torch trains in).
ACTOR_DTYPES: dict[str, type[np.floating]] = {"float64": np.float64, "float32": np.float32}


def actor_forward(
    agent: Agent, dtype: type[np.floating] = np.float64
) -> Callable[[np.ndarray], np.ndarray]:
    """The agent's actor as a numpy function of raw observations (n, D), float64, its
    weights read once: the actor's output (float64) before any prior or bound. ``dtype``:
    of its weights and products after the (float64) normalisation (``policy_batch``'s
    ``actor_dtype``)."""
    shift = agent.shift.detach().double().numpy()
    scale = agent.scale.detach().double().numpy()
    layers: list[tuple[np.ndarray, np.ndarray] | None] = []  # None: tanh
    for m in agent.actor:
        if isinstance(m, torch.nn.Linear):
            w = np.ascontiguousarray(m.weight.detach().double().numpy().T, dtype=dtype)
            layers.append((w, m.bias.detach().double().numpy().astype(dtype)))
        elif isinstance(m, torch.nn.Tanh):
            layers.append(None)
        else:
            raise TypeError(f"policy_batch: actor layer {type(m).__name__} not supported")

    last = max(i for i, layer in enumerate(layers) if layer is not None)
    # The hidden layers' outputs, kept between calls (grown as needed): written in place, the
    # same products and sums as fresh arrays, without a step's allocations. Their biases as
    # rows as many (``tiled``): the same sums as the broadcast bias, a contiguous add
    # (~1 us less a layer at 42 rows, numpy 2.4).
    kept = [np.empty((0, 0 if layer is None else len(layer[1])), dtype) for layer in layers]
    tiled = list(kept)
    f64 = dtype is np.float64
    # float32: the normalised observations, kept between calls as the layers' outputs are
    # (``normed``): the float64 quotient is cast as it is written, astype's values to the bit
    # (round to nearest), one array pass and allocation fewer a step.
    normed = [np.empty((0, len(shift)), dtype)]

    def forward(obs: np.ndarray) -> np.ndarray:
        x0 = np.subtract(obs, shift)
        n = len(x0)
        if f64:
            np.divide(x0, scale, out=x0)
        else:
            if len(normed[0]) < n:
                normed[0] = np.empty((max(n, ACTOR_ROWS // 2), len(shift)), dtype)
            x0 = np.divide(x0, scale, out=normed[0][:n])
        if n <= ACTOR_ROWS:  # one product per layer
            x = x0
            for i, layer in enumerate(layers):
                if layer is None:
                    np.tanh(x, out=x)
                    continue
                if i == last:  # a fresh output
                    x = np.matmul(x, layer[0])
                    np.add(x, layer[1], out=x)
                    continue
                if len(kept[i]) < n:
                    rows = max(n, ACTOR_ROWS // 2)
                    kept[i] = np.empty((rows, len(layer[1])), dtype)
                    tiled[i] = np.tile(layer[1], (rows, 1))
                x = np.matmul(x, layer[0], out=kept[i][:n])
                np.add(x, tiled[i][:n], out=x)
            return x[:, 0] if f64 else x[:, 0].astype(np.float64)
        out = np.empty(n)
        for start in range(0, n, ACTOR_ROWS):
            x = x0[start : start + ACTOR_ROWS]
            for layer in layers:
                x = np.tanh(x, out=x) if layer is None else x @ layer[0] + layer[1]
            out[start : start + ACTOR_ROWS] = x[:, 0]
        return out

    return forward


def prior_forward(agent: Agent) -> Callable[[np.ndarray], np.ndarray] | None:
    """The agent's prior acceleration [m/s^2] as a numpy function of raw observations
    (``evaluation.idm_fit``'s twins of ``policy.prior``'s torch functions, which
    tests/policy/test_prior.py holds equal); None without a prior."""
    if agent.prior == "none":
        return None
    p = prior_buffer(agent)
    if agent.prior == "idm":
        idm = IdmParams(**{k: v for k, v in p.items() if k != "veh_length_m"})
        return lambda obs: idm_policy_accel(obs, idm, p["veh_length_m"])
    fitted = {k: v for k, v in p.items() if k not in ("veh_length_m", "dt_s")}
    if agent.prior == "krauss":
        krauss = KraussParams(**fitted)
        if agent.driver_tau is not None:  # each row's own tau where a column carries it
            d = agent.obs_dim

            def per_row(obs: np.ndarray) -> np.ndarray:
                own = krauss
                if obs.shape[-1] > d:
                    own = dataclasses.replace(krauss, tau_s=obs[..., d])
                return krauss_policy_accel(obs, own, p["veh_length_m"], p["dt_s"])

            return per_row
        return krauss_batch(krauss, p["veh_length_m"], p["dt_s"])
    gipps = GippsParams(**fitted)
    return lambda obs: gipps_policy_accel(obs, gipps, p["veh_length_m"], p["dt_s"])


def krauss_batch(
    p: KraussParams, veh_length_m: float, dt_s: float
) -> Callable[[np.ndarray], np.ndarray]:
    """``evaluation.krauss_fit.krauss_policy_accel`` to the bit, as a function of
    observations (n, >= 4), cheaper a step: the same operations in the same order, its
    constants numpy 0-d arrays made once (a Python float operand costs numpy 2.4 a
    conversion and a weak-scalar promotion each call, ~0.3 us of a ~0.7 us call at 42
    rows) and the leader's speed squared as a product (``x**2``'s power dispatch, the same
    value). 11.1 -> 8.1 us a step on Bremen's recorded observations (tight loop); each
    numpy microsecond between SUMO's steps also costs SUMO's step about as much again
    (stop 43, ``scripts/bench_sumo_step.py``). Fresh arrays, not ``out=`` buffers: at this
    size the keyword and the views cost more than numpy's cached allocations (measured,
    12.7 us). tests/deploy/test_numpy_actor.py holds the two equal."""

    def c(x: float) -> np.ndarray:  # float64 like the observations: the same promotion
        return np.array(float(x))

    bt = p.decel_mps2 * p.tau_s
    speed_factor, floor, accel, decel2 = (
        c(p.speed_factor),
        c(0.1),
        c(p.accel_mps2),
        c(2.0 * p.decel_mps2),
    )
    length, min_gap, zero = c(veh_length_m), c(p.min_gap_m), c(0.0)
    relax, dt, least = c(max(p.relax_s, dt_s)), c(dt_s), c(-EMERGENCY_DECEL_MPS2)
    bt2, minus_bt = c(bt**2), c(-bt)

    consts = (speed_factor, floor, accel, relax, length, min_gap, bt2, decel2, minus_bt, dt, least)

    def prior(obs: np.ndarray) -> np.ndarray:
        if kernels is not None:  # the compiled pass (road/kernels.c): the same values
            out = np.empty(len(obs))
            if kernels.krauss_prior(obs, *consts, out):
                return out
        v = obs[:, 0]
        free = np.minimum(accel, (np.maximum(speed_factor * obs[:, 1], floor) - v) / relax)
        gap = np.maximum(obs[:, 2] - length - min_gap, zero)
        v_leader = np.maximum(v - obs[:, 3], zero)
        safe = minus_bt + np.sqrt(bt2 + v_leader * v_leader + decel2 * gap)
        return np.maximum(np.minimum(free, (safe - v) / dt), least)

    return prior


def policy_batch(agent: Agent, actor_dtype: str = "float64") -> ActionBatch:
    """The policy's deterministic mean action (``Agent.mean_action``) for every driven
    vehicle, one numpy call per step.

    ``actor_dtype`` "float32" (the scenario's ``deploy.actor_dtype``, its default, as
    ``deploy.stage.method_drive`` passes it; ``scripts/bench_deploy.py --actor-dtype``): the
    actor's weights and products in float32, the prior and the rest float64. Not the same
    actions: within 1e-7 m/s^2 of float64's on Bremen's 60,368 (run 0, lead40's policy);
    a Bremen policy run 24.6 us a step cheaper (median of 12 interleaved pairs, all 12
    faster; SUMO's own step 8 us of it).

    With a ``driver_tau`` buffer the actor reads the first D columns and the prior its
    tau from a trailing one where the observation has it (``act.driver_taus``: the run's
    ``DriverTaus`` for the drivers to append it).

    Numpy, float64, the weights read once: torch's fixed cost per call (~0.1 ms for the
    actor, ~0.3 ms more for a prior's dozen small ops) was most of a step's policy time
    below 500 driven vehicles (``scripts/bench_deploy.py``). Equal to
    ``Agent.mean_action`` in float64 (tests/deploy/test_deploy_run.py)."""
    if actor_dtype not in ACTOR_DTYPES:
        raise ValueError(f"actor_dtype {actor_dtype!r}: accepted {', '.join(ACTOR_DTYPES)}")
    actor, prior = actor_forward(agent, ACTOR_DTYPES[actor_dtype]), prior_forward(agent)
    bound = float(agent.residual_bound) if prior is not None else math.inf
    if agent.driver_tau is not None:  # a tau column may follow: the actor reads D columns
        actor = partial(_features, actor, agent.obs_dim)

    def act(obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        if prior is None:
            return actor(obs)
        if bound <= 0.0:  # the fitted prior alone (an ablation)
            return prior(obs)
        out = actor(obs)
        if bound == 1.0:  # x / 1 and 1 y are x and y: the same values, two calls fewer
            out = np.tanh(out)
        elif math.isfinite(bound):
            out = bound * np.tanh(out / bound)
        return out + prior(obs)

    # policy.driver_speed: each driven vehicle's factor, set by its driver.
    q = agent.driver_speed
    act.driver_speeds = None if q is None else partial(DriverSpeeds, q.double().numpy())
    # policy.driver_follow: each driven vehicle's own tau, a trailing column (observe_rows).
    t = agent.driver_tau
    handover = prior_buffer(agent) if agent.prior == "krauss" else None
    act.driver_taus = None if t is None else partial(DriverTaus, t.double().numpy(), prior=handover)
    # The gap the policy stops at: its prior's minGap (``deploy.observe.observe_rows``).
    act.stop_gap_m = prior_stop_gap_m(agent)
    # deploy.command_dawdle = "auto": the Krauss prior's a (``deploy.safety``); None: none.
    act.prior_accel_mps2 = handover["accel_mps2"] if handover is not None else None
    return act


def _features(actor: Callable[[np.ndarray], np.ndarray], d: int, obs: np.ndarray) -> np.ndarray:
    """``actor`` on the first ``d`` columns of ``obs`` (the features; a tau may follow)."""
    return actor(obs[:, :d])


def prior_stop_gap_m(agent: Agent) -> float | None:
    """The bumper gap [m] at which the agent's prior stops behind a standing leader, its
    fitted minGap (Krauss, Gipps; IDM's s0); None without a prior."""
    if agent.prior == "none":
        return None
    return float(prior_buffer(agent)["min_gap_m"])


def action_std(agent: Agent) -> float:
    """The std [m/s^2] of the policy's Gaussian (state-independent, learned from the
    observed vehicles' likelihood): what ``deploy.action = "sample"`` draws with."""
    return float(agent.log_std.detach().double().exp().item())

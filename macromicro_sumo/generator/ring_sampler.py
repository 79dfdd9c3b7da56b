"""The ring generator's inference: Algorithm 3 (``complete``) and the baselines.

Algorithm 3, batched over snapshots: every step proposes T_max candidates at once (the
proposal distribution does not change between trials, so this equals resampling one at
a time) and keeps the first whose touched gaps and speed are within bounds (the
look-ahead of ``ring_posterior``); if none is, the last candidate is projected onto the
nearest feasible point and counted.

Extension (``complete(..., truncate=True)``, the default): the split point of each trial
is drawn from the position proposal truncated to the chosen gap's feasible split points,
the T_max -> infinity limit of resampling it (inverse CDF over the disjoint feasible
pieces, in log space so that any tail is exact). The gap is chosen as in the plain
algorithm, from the network's scores over the gaps with some feasible split point (the
same limit for the discrete part). Why: the paper's loss barely penalises a gap a few
metres past d_min or d_max (L_min, L_max are squared relative violations), so the trained
position spread collapses onto points just outside the bounds and the T_max trials are
nearly identical. The check still judges every candidate and projection stays the
counted fallback (a gap whose feasible pieces carry no mass at all under the proposal).
``truncate=False`` is the plain Algorithm 3. ``Completion.accept_prob`` keeps, per step,
the probability that one plain trial would have passed (sum_j p_j m_j, m_j the mass the
position proposal puts on gap j's feasible points), so how much the truncation does is
on record: ``rejection_success`` is the chance that plain Algorithm 3 would have placed
every vehicle of a completion without projection.

Inference runs in numpy (``ring_model`` says why); with ``gap_choice = "posterior"`` the
gap scores are ``ring_posterior.gap_posterior``'s. The baselines (``complete_uniform``,
``complete_equal_gap``) return the same ``Completion``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.special import log_ndtr, ndtri_exp

from macromicro_sumo.data.ring import Snapshots
from macromicro_sumo.generator.ring_gaps import PsiTensors, row_index
from macromicro_sumo.generator.ring_model import (
    FRAC_LOG_STD,
    SPEED_LOG_STD,
    GeneratorNet,
    observe,
    speed_base,
)
from macromicro_sumo.generator.ring_posterior import (
    GEOMETRY_TOL_M,
    Lookahead,
    SplitTable,
    gap_posterior,
    lookahead,
)

# --------------------------------------------------------------------------- inference


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _log_softmax(x: np.ndarray) -> np.ndarray:
    top = np.maximum.reduce(x, axis=-1, keepdims=True)
    return x - top - np.log(np.add.reduce(np.exp(x - top), axis=-1, keepdims=True))


def _categorical(log_w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(..., S) draws from the categoricals exp(log_w) (..., C), unnormalised, by inverse
    CDF of the uniforms ``u`` (..., S). A row without mass draws 0."""
    cdf = np.cumsum(np.exp(log_w - np.maximum.reduce(log_w, axis=-1, keepdims=True)), axis=-1)
    cdf /= cdf[..., -1:]
    return np.add.reduce(u[..., None] >= cdf[..., None, :], axis=-1)


class FeasibleSplits:
    """Each gap's feasible split points in units of its position proposal (a standard
    normal z with fraction = sigmoid(mu + sigma z)), as disjoint pieces (B, N, P).

    The look-ahead's intervals (one per count pair, overlapping) are sorted and cut into
    disjoint pieces; each piece's probability and the inverse CDF within it are computed
    from log Phi (the lower tail, mirrored for pieces above the mean), so a piece far in
    the tail keeps an exact, tiny mass and its draws stay inside it. The intervals are
    widened by the check's tolerance, so a gap that fits exactly keeps a feasible piece.
    """

    def __init__(self, look: Lookahead, mu: np.ndarray, sigma: np.ndarray) -> None:
        tol = GEOMETRY_TOL_M
        lo = np.where(look.ok, look.lo - tol, np.inf)
        hi = np.where(look.ok, look.hi + tol, -np.inf)
        b, n, _ = lo.shape
        ix = (row_index(b, 3), row_index(n), lo.argsort(axis=-1))
        lo, hi = lo[ix], np.maximum.accumulate(hi[ix], axis=-1)
        # Sorted by start, piece i keeps what pieces before it do not cover.
        lo[..., 1:] = np.maximum(lo[..., 1:], hi[..., :-1])
        good = hi > lo
        g = look.gap[..., None]
        ends = np.array([np.where(good, lo, 0.25 * g), np.where(good, hi, 0.75 * g)])  # [m]
        z = (np.log(ends) - np.log(g - ends) - mu[..., None]) / sigma[..., None]
        flip = z[0] > 0
        z = np.where(flip, -z[::-1], z)  # mirrored above the mean: z[0] <= 0
        log_phi = log_ndtr(z)
        lm = log_phi[1] + np.log(-np.expm1(log_phi[0] - log_phi[1]))
        self.log_mass = np.where(good & (lm == lm), lm, -np.inf)  # (B, N, P)
        # What ``sample`` looks up for a chosen piece, in one array: log Phi at both ends,
        # both ends (mirrored or not), whether mirrored, both ends in metres.
        self.pieces = np.concatenate([log_phi, z, flip[None], ends])
        # (B, N): log of the mass the gap's position proposal puts on feasible points.
        log_m = np.logaddexp.reduce(self.log_mass, axis=-1)
        # Each gap's pieces as a CDF (B, N, P), to draw a piece by its mass.
        self.cdf = np.cumsum(np.exp(self.log_mass - log_m[..., None]), axis=-1)
        self.cdf /= self.cdf[..., -1:]
        empty = np.where(look.empty_ok, 0.0, -np.inf)[:, None]
        self.log_m = np.where(look.empty[:, None], empty, log_m)

    def sample(
        self,
        choice: np.ndarray,
        u_piece: np.ndarray,
        u: np.ndarray,
        mu: np.ndarray,
        sigma: np.ndarray,
        gap: np.ndarray,
    ) -> np.ndarray:
        """(B, S) split points [m] in gaps ``choice`` drawn from the truncated proposal
        (``mu``, ``sigma``, ``gap`` of the chosen gaps, (B, S)): a piece by its mass, then
        the inverse CDF within it. Call under np.errstate (rows without mass give NaN)."""
        rows = row_index(len(choice))
        piece = np.add.reduce(u_piece[..., None] >= self.cdf[rows, choice], axis=-1)
        log_a, log_b, za, zb, flip, lo, hi = self.pieces[:, rows, choice, piece]
        # Phi(z) = (1 - u) Phi(za) + u Phi(zb), in logs.
        z = ndtri_exp(np.logaddexp(np.log1p(-u) + log_a, np.log(u) + log_b))
        z = np.minimum(np.maximum(z, za), zb)
        z = np.where(flip > 0, -z, z)
        return np.minimum(np.maximum(gap * _sigmoid(mu + sigma * z), lo), hi)


@dataclass
class Completion:
    arc_m: np.ndarray
    speed_mps: np.ndarray
    projected: np.ndarray  # (B,) number of hidden vehicles that needed projection
    wall_s: float
    # (B, K_max) per step, the probability that one trial of the plain (untruncated)
    # proposal passes the check; NaN where the snapshot had no vehicle left to place.
    accept_prob: np.ndarray | None = None
    speed_fixes: np.ndarray | None = None  # (B,) speeds changed by ``safe_speeds``


def complete(
    net: GeneratorNet,
    snaps: Snapshots,
    t_max: int,
    seed: int,
    truncate: bool = True,
    standstill_m: float = 0.0,
    brake_mps2: float = 0.0,
    headway_s: float = 0.0,
) -> Completion:
    """Algorithm 3, batched: rejection sampling against Psi's bounds, projection as fallback.

    ``truncate`` draws each trial from the proposal restricted to the feasible split points
    (the T_max -> infinity limit of rejection; module docstring); False is the plain
    algorithm. ``standstill_m`` > 0 (the fleet's standstill spacing: vehicle length plus
    the smallest standstill gap) keeps every new spacing at least that long, where Psi's
    d_min allows less or no split point meets Psi's bounds; ``brake_mps2`` > 0 then makes
    the generated speeds kinematically consistent (``safe_speeds``, with the fleet's
    shortest time headway ``headway_s``). All 0: the plain algorithm's geometry and speeds.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(int(seed))
    hidden = np.asarray(snaps.hidden, dtype=bool)
    # Geometry in float64 (the network sees float32 features): accepted gaps are then
    # within Psi's bounds to rounding, not to float32's ~1e-4 m on a ring.
    arc = np.where(hidden, 0.0, snaps.arc_m).astype(np.float64)
    speed = np.where(hidden, 0.0, snaps.speed_mps).astype(np.float64)
    psi = PsiTensors.arrays(snaps)
    b, n = arc.shape
    k = hidden.sum(axis=1)
    k_max = int(k.max()) if b else 0
    state = _Scene(arc, speed, ~hidden, hidden, snaps.length_m)
    # Psi's d_min, measured at the detectors, can be shorter than a vehicle standing behind
    # another (ring_sugiyama: 4.6 m for 5 m vehicles): the look-ahead never goes below the
    # standstill spacing (a no-op where d_min is far above it, as on the paper's ring).
    d_min = np.maximum(psi.d_min, standstill_m)
    table = SplitTable(d_min, np.maximum(psi.d_max, d_min), max(k_max - 1, 0), snaps.length_m)
    weights = net.numpy_weights()
    projected = np.zeros(b, dtype=int)
    accept_prob = np.full((b, k_max), np.nan)
    rank = np.where(hidden, hidden.cumsum(axis=1), 0)  # hidden slots fill in slot order
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for step in range(k_max):
            active = k > step
            out = _algorithm3_step(
                net, weights, state, psi, table, k - step, t_max, truncate, rng, standstill_m
            )
            projected += active & out.projected
            accept_prob[:, step] = np.where(active, out.accept_prob, np.nan)
            state.place(rank == step + 1, out.arc, out.speed)
    # Observed vehicles never move: the input values, bit for bit.
    arc_out = np.where(hidden, state.arc % snaps.length_m, snaps.arc_m)
    speed_out = np.where(hidden, state.speed, snaps.speed_mps)
    fixes = None
    if brake_mps2 > 0:
        speed_out, fixes = safe_speeds(
            arc_out, speed_out, hidden, snaps.length_m, standstill_m, brake_mps2, headway_s
        )
    return Completion(arc_out, speed_out, projected, time.perf_counter() - t0, accept_prob, fixes)


def safe_speeds(
    arc: np.ndarray,
    speed: np.ndarray,
    hidden: np.ndarray,
    length_m: float,
    standstill_m: float,
    brake_mps2: float,
    headway_s: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Generated speeds made kinematically consistent with their neighbours (B, N) on the
    ring; returns them and the number of speeds changed per scene (B,).

    Psi's speed bounds say nothing about pairs: on a dense ring a generated vehicle drawn
    at 0.3 m/s 6 m ahead of an observed one at 6 m/s is within them and is hit in the first
    second (ring_sugiyama). The condition is ``section_sampler.safe_speeds``' stopping
    distance, v^2 <= v_leader^2 + 2 b (spacing - standstill spacing), b the action bound's
    braking: a generated leader is first raised where its observed follower could not stop
    behind it, then every generated vehicle is capped to what lets it stop behind its
    leader (repeated along chains of generated vehicles, so a capped leader caps its
    followers). The cap wins where the two conflict: a generated vehicle must be able to
    stop, while an observed follower that would run into it brakes in the environment.
    With ``headway_s`` > 0 a generated vehicle is also no faster than a driver keeping that
    time headway beyond the standstill spacing, v <= (spacing - standstill) / headway: the
    stopping distance admits 5.8 m/s with 1.7 m to a leader at 6.6 m/s, where every driver
    of the fleet brakes at once (ring_sugiyama's ground truth exceeds this cap in 1.3% of
    vehicle-steps, by a median 0.14 m/s; the paper's ring never).
    """
    b, n = arc.shape
    order = np.argsort(arc, axis=1)
    rows = row_index(b)
    leader = np.empty_like(order)
    leader[rows, order] = np.roll(order, -1, axis=1)
    spacing = np.mod(arc[rows, leader] - arc, length_m)
    spacing = np.where(leader == np.arange(n), length_m, spacing)  # a lone vehicle
    room = 2.0 * brake_mps2 * np.maximum(spacing - standstill_m, 0.0)
    v = speed.copy()
    # An observed follower's speed is given: one pass raises each generated leader.
    follower = np.empty_like(order)
    follower[rows, leader] = np.arange(n)
    floor = np.sqrt(np.maximum(v**2 - room, 0.0))[rows, follower]
    v = np.where(hidden & ~hidden[rows, follower], np.maximum(v, floor), v)
    headway_cap = np.maximum(spacing - standstill_m, 0.0) / headway_s if headway_s > 0 else np.inf
    for _ in range(n):  # caps travel backwards along a chain of generated vehicles
        cap = np.minimum(np.sqrt(v[rows, leader] ** 2 + room), headway_cap)
        capped = hidden & (v > cap)
        if not capped.any():
            break
        v = np.where(capped, cap, v)
    return v, np.add.reduce(v != speed, axis=1)


@dataclass
class _Scene:
    """A scene being completed (numpy, (B, N) each)."""

    arc: np.ndarray
    speed: np.ndarray
    present: np.ndarray
    hidden: np.ndarray
    length_m: float

    def place(self, onehot: np.ndarray, arc: np.ndarray, speed: np.ndarray) -> None:
        self.arc = np.where(onehot, arc[:, None], self.arc)
        self.speed = np.where(onehot, speed[:, None], self.speed)
        self.present = self.present | onehot


@dataclass
class _Placed:
    arc: np.ndarray  # (B,) [m]
    speed: np.ndarray  # (B,)
    projected: np.ndarray  # (B,) no trial passed: projected
    accept_prob: np.ndarray  # (B,) one plain trial's chance to pass


def _algorithm3_step(
    net: GeneratorNet,
    weights: tuple[np.ndarray, ...],
    scene: _Scene,
    psi: PsiTensors,
    table: SplitTable,
    remaining: np.ndarray,
    t_max: int,
    truncate: bool,
    rng: np.random.Generator,
    standstill_m: float = 0.0,
) -> _Placed:
    """One vehicle for every scene: T_max trials, the first that passes, else projection."""
    b = len(remaining)
    rows = np.arange(b)
    remaining = np.maximum(remaining, 0)
    anchor = rng.random(b) * scene.length_m
    obs = observe(scene.arc, scene.speed, scene.present, remaining, psi, scene.length_m, anchor)
    _, _, gap, valid, start = obs.geometry
    look = lookahead(
        table,
        obs.geometry,
        scene.present,
        scene.hidden & scene.present,
        np.maximum(remaining - 1, 0),
    )
    out = net.forward_numpy(obs.gap_feat, obs.glob, weights).astype(np.float64)
    if net.gap_choice == "posterior":
        out[..., 0] = gap_posterior(gap, valid, remaining, psi)
    allowed = look.allowed & valid
    if standstill_m > 0:
        # No gap meets Psi's bounds: fall back on gaps that hold a vehicle at standstill
        # spacing on both sides (any gap only where none does).
        fits = valid & (gap >= 2 * standstill_m)
        allowed = allowed | (fits & ~np.logical_or.reduce(allowed, axis=1, keepdims=True))
    choosable = valid & (allowed | ~np.logical_or.reduce(allowed, axis=1, keepdims=True))
    log_p = _log_softmax(np.where(choosable, out[..., 0], -np.inf))
    mu = out[..., 1]
    sigma = np.exp(np.minimum(np.maximum(out[..., 2], FRAC_LOG_STD[0]), FRAC_LOG_STD[1]))
    splits = FeasibleSplits(look, mu, sigma)
    log_acc = np.logaddexp.reduce(log_p + splits.log_m, axis=1)
    # Trials: the gap, the split point (truncated or plain) and the speed.
    u = rng.random((3, b, t_max))
    eps = rng.standard_normal((2, b, t_max))
    choice = _categorical(log_p, u[0])  # (B, S)
    sel = (rows[:, None], choice)
    g, mu_c, sig_c, out_c = gap[sel], mu[sel], sigma[sel], out[sel]
    trunc = (log_acc > -np.inf) & ~look.empty if truncate else np.zeros(b, dtype=bool)
    if trunc.all():
        a1 = splits.sample(choice, u[1], u[2], mu_c, sig_c, g)
    else:
        a1 = g * np.minimum(np.maximum(_sigmoid(mu_c + sig_c * eps[0]), 1e-3), 1 - 1e-3)
        if trunc.any():
            a1 = np.where(trunc[:, None], splits.sample(choice, u[1], u[2], mu_c, sig_c, g), a1)
    v_min, v_max = psi.v_min[:, None], psi.v_max[:, None]
    log_std_v = np.minimum(np.maximum(out_c[..., 4], SPEED_LOG_STD[0]), SPEED_LOG_STD[1])
    v_u = _sigmoid(
        speed_base(obs.need_v, psi)[:, None] + out_c[..., 3] + np.exp(log_std_v) * eps[1]
    )
    v = np.minimum(v_min + psi.v_range[:, None] * v_u, v_max)
    ok = look.accepts(choice, a1) & (v >= v_min) & (v <= v_max)
    any_ok = np.logical_or.reduce(ok, axis=1)
    # The first accepted candidate, else the last one, projected: the nearest split
    # point of its gap that passes, its speed clipped to the bounds.
    pick = np.where(any_ok, ok.argmax(axis=1), t_max - 1)
    c, a, new_v = choice[rows, pick], a1[rows, pick], v[rows, pick]
    if not any_ok.all():
        a = np.where(any_ok, a, look.project(c, a, standstill_m))
        new_v = np.where(any_ok, new_v, np.minimum(np.maximum(new_v, psi.v_min), psi.v_max))
    return _Placed((start[rows, c] + a) % scene.length_m, new_v, ~any_ok, np.exp(log_acc))


def rejection_success(comp: Completion, t_max: int) -> np.ndarray:
    """(B,) the probability that the plain Algorithm 3 (T_max untruncated trials per step)
    would have placed every vehicle of this completion's path without projection."""
    p = np.nan_to_num(comp.accept_prob, nan=1.0)
    return np.prod(1.0 - (1.0 - p) ** t_max, axis=1)


# --------------------------------------------------------------------------- baselines


def complete_uniform(snaps: Snapshots, seed: int) -> Completion:
    """Baseline: hidden vehicles at uniform random positions and speeds within Psi's bounds."""
    t0 = time.perf_counter()
    rng = np.random.default_rng([seed, 101])
    b, n = snaps.arc_m.shape
    arc = np.where(snaps.hidden, rng.uniform(0, snaps.length_m, (b, n)), snaps.arc_m)
    v = rng.uniform(snaps.psi[:, 4:5], snaps.psi[:, 5:6], (b, n))
    speed = np.where(snaps.hidden, v, snaps.speed_mps)
    return Completion(arc, speed, np.zeros(b, dtype=int), time.perf_counter() - t0)


def complete_equal_gap(snaps: Snapshots, seed: int) -> Completion:
    """Baseline: water-fill the observed gaps with evenly spaced vehicles at the speed
    that makes the fleet mean equal Psi's mean speed (clipped to the bounds)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng([seed, 202])
    b, n = snaps.arc_m.shape
    arc = snaps.arc_m.copy()
    speed = snaps.speed_mps.copy()
    length = snaps.length_m
    for i in range(b):
        hid = np.flatnonzero(snaps.hidden[i])
        k = len(hid)
        if k == 0:
            continue
        obs = np.sort(snaps.arc_m[i, ~snaps.hidden[i]])
        if len(obs) == 0:
            starts, arcs = np.array([rng.uniform(0, length)]), np.array([length])
            counts = np.array([k - 1])
        else:
            starts = obs
            arcs = np.mod(np.roll(obs, -1) - obs, length)
            arcs[arcs == 0] = length if len(obs) == 1 else 0.0
            counts = np.zeros(len(obs), dtype=int)
            for _ in range(k):
                counts[np.argmax(arcs / (counts + 1))] += 1
        pos = []
        for s0, ln, c in zip(starts, arcs, counts, strict=True):
            if len(obs) == 0:
                pos += [s0 + ln * j / k for j in range(k)]
            else:
                pos += [s0 + ln * j / (c + 1) for j in range(1, c + 1)]
        arc[i, hid] = np.mod(pos, length)
        v_obs = snaps.speed_mps[i, ~snaps.hidden[i]].sum()
        speed[i, hid] = np.clip((n * snaps.psi[i, 0] - v_obs) / k, snaps.psi[i, 4], snaps.psi[i, 5])
    return Completion(arc, speed, np.zeros(b, dtype=int), time.perf_counter() - t0)

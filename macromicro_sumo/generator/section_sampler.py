"""Stage I on a road section: Algorithm 3 (``complete_section``), safe speeds, baseline.

Rejection (Algorithm 3). Each vehicle gets up to T_max trials; a trial fails if its
position lies on an edge that lacks the gap's lane (a lane drop inside the gap), breaks
a bound, or (with a braking bound) leaves no speed at which the gap's follower can stop
behind it and it behind the gap's leader (``kinematic_speeds``; its speed is clipped
into that window); after T_max failures the last trial is projected onto the nearest
feasible point (of its gap, else of the most likely gap that has one) and counted.
Gaps with no room at all (a gap shorter than two minimum spacings) are not chosen
unless no gap has room (the section is fuller than psi allows: projection, counted). A
vehicle with no admissible point in any gap is not placed (``dropped``, counted): put
where it was proposed, it would overlap its neighbours, an impossible start scene that
the environment then reports as a collision (an over-estimated hidden count did that).

Inference is torch under no_grad, the T_max trials of a step at once, batched over
snapshots, with the proposal of ``section_model``. ``safe_speeds`` then makes generated
speeds kinematically consistent with their lane neighbours; ``uniform_completion`` is the
baseline.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import torch

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.data.vtypes import typical
from macromicro_sumo.generator.section_bounds import bounded_gaps
from macromicro_sumo.generator.section_model import SectionGeneratorNet, propose
from macromicro_sumo.generator.section_pairs import (
    SectionCompletion,
    drop_unsafe_pairs,
    safe_speeds,
)
from macromicro_sumo.generator.section_rollout import Scene
from macromicro_sumo.generator.section_scene import (
    PSI_INDEX,
    TOL_M,
    Gaps,
    Psi,
    Road,
    extra_lengths,
    generated_extra,
    scene_stops,
    shortest_length,
    stop_room_m,
)
from macromicro_sumo.road.section import Section

PROJECTION_PROBES = 32  # points per gap a projection tries for a kinematically consistent one


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Run torch on one thread inside the block: the per-step arrays are small, and on a
    shared machine torch's thread pool made completion ten times slower (measured)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# --------------------------------------------------------------------------- inference


def k_of(snaps: SectionSnapshots, source: str) -> np.ndarray:
    """The hidden count per snapshot that the scenario's ``k_source`` asks for."""
    return np.asarray(snaps.k_true if source == "truth" else snaps.k_est, dtype=np.int64)


def _project(
    road: Road,
    gaps: Gaps,
    probs: torch.Tensor,
    row: int,
    choice: int,
    arc: float,
    window=None,
) -> tuple[float, int]:
    """The feasible point nearest to ``arc`` in gap ``choice``, else in the most likely gap
    that has one (its point nearest to the middle of its admissible part), and that gap;
    ``arc`` (gap -1) if none.

    With ``window(gap, offsets) -> (lo, hi)`` (the kinematic speed window of points that
    far into a gap), a point where some speed keeps both neighbours consistent is
    preferred (``PROJECTION_PROBES`` points per gap), in the same order of gaps."""
    start, lo, hi = gaps.start[row].numpy(), gaps.lo[row].numpy(), gaps.hi[row].numpy()
    lanes, valid = gaps.lane[row].numpy(), gaps.valid[row].numpy()
    order = [choice] + [
        int(j) for j in np.argsort(-probs[row].numpy(), kind="stable") if valid[j] and j != choice
    ]
    target = arc
    if road.closed and choice < len(start):  # unwrap onto the chosen gap
        target = start[choice] + np.mod(arc - start[choice], road.length_m)
    first = None
    for j in order:
        a, b = start[j] + lo[j], start[j] + hi[j]
        aim = target if j == choice else 0.5 * (a + b)
        x = road.nearest_on_lane(int(lanes[j]), a, b, aim)
        if x is None:
            continue
        if window is None:
            return _wrapped(road, x), j
        first = (x, j) if first is None else first
        probe = np.linspace(a, b, PROJECTION_PROBES)
        v_lo, v_hi = window(j, torch.as_tensor(probe - start[j]))
        ok = v_lo <= v_hi
        for k in np.argsort(np.abs(probe - aim), kind="stable"):
            y = float(probe[k])
            if ok[k] and road.nearest_on_lane(int(lanes[j]), y, y, y) is not None:
                return _wrapped(road, y), j
    return (arc, -1) if first is None else (_wrapped(road, first[0]), first[1])


def _wrapped(road: Road, x: float) -> float:
    return float(np.mod(x, road.length_m)) if road.closed else x


@dataclass
class GeneratorCompletion:
    """``completion(snaps)`` for ``section_env.build_section_bank``: Algorithm 3 with the
    hidden count ``k_source`` asks for (each snapshot carries both), then safe speeds with
    one step of reaction (what SUMO's safe speed in the environment allows). Counts the
    vehicles it generated and those it dropped (``SectionCompletion.dropped``: no room,
    or a pair it could not make drivable) over its calls, for the evaluation's manifest."""

    net: SectionGeneratorNet
    section: Section
    sc: Any
    k_source: str
    seed: int
    generated_length_m: float | None = None  # ``complete_section``'s
    generated: int = 0
    dropped: int = 0

    def __call__(self, s: SectionSnapshots):
        c = complete_section(
            self.net,
            self.section,
            s,
            k_of(s, self.k_source),
            self.sc.generator.t_max,
            self.seed,
            -self.sc.bounds.accel_mps2[0],
            self.sc.simulation.step_length_s,
            self.generated_length_m,
        )
        self.generated += int(c.generated.sum())
        self.dropped += 0 if c.dropped is None else int(c.dropped.sum())
        return c.lane, c.arc_m, c.speed_mps, c.valid, c.generated


generator_completion = GeneratorCompletion


def generated_length(truth: Any) -> float | None:
    """The generated vehicles' length in the environment [m]: the vType with the most
    vehicles on the section (``data.vtypes.typical``, as ``env.section_bank.typical_length``
    gives the Stage II envs and evaluation); None without vTypes. Stage I's own
    scoring (``section_stage``, ``complete``) completes with it, as Stage II does."""
    vt = getattr(truth, "vtypes", None)
    if vt is None or not len(vt) or "length_m" not in vt or "vehicles" not in vt:
        return None
    return float(typical(vt, "length_m"))


def _window_of(
    g: Gaps,
    psi: Psi,
    row: int,
    kin: tuple[float, float],
    stops: tuple[torch.Tensor, torch.Tensor] | None,
    road: Road,
    gap: int,
    offsets: torch.Tensor,
) -> tuple[np.ndarray, np.ndarray]:
    """``kinematic_speeds`` of points ``offsets`` m into gap ``gap`` of scene ``row``."""
    one = Gaps(*(getattr(g, f)[row : row + 1] for f in g.__dataclass_fields__))
    choice = torch.full((1, len(offsets)), gap, dtype=torch.int64)
    at = None if stops is None else (stops[0][row : row + 1], stops[1][row : row + 1])
    psi_r = psi.take(torch.tensor([row]))
    lo, hi = kinematic_speeds(one, choice, offsets[None], psi_r, *kin, at, road)
    return lo[0].numpy(), hi[0].numpy()


def kinematic_speeds(
    gaps: Gaps,
    choice: torch.Tensor,
    a: torch.Tensor,
    psi: Psi,
    brake_mps2: float,
    reaction_s: float,
    stops: tuple[torch.Tensor, torch.Tensor] | None = None,
    road: Road | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(lo, hi) speeds [m/s] of candidates at ``a`` m into their gap ``choice`` (B, n) that
    keep both new pairs kinematically consistent (``safe_speeds``'s condition): the
    gap's follower can stop behind the candidate, v^2 >= v_f^2 + 2 b tau v_f - room_f, and
    the candidate behind the gap's leader, v^2 + 2 b tau v <= v_l^2 + room_l, within psi's
    speed bounds; lo > hi: no speed does, the position is refused.

    Why positions and not only speeds: in a dense platoon (Spreewaldring, 0.5-2 m bumper
    gaps) a vehicle put into a short gap behind a slow leader and ahead of a fast observed
    follower has no such speed; whichever speed ``safe_speeds`` then gives it, one of
    them must brake far beyond the bound in the first step and the vehicle behind that
    one runs into it. ``stops`` (with ``road``): the scenes' red or yellow stop lines
    (``stop_room_m``); the candidate must also stop before the next one on its lane (a
    car given 12 m/s 1 m before a red light stops there in one step, and the car behind
    it does not: game/cross).
    """
    b, tau = brake_mps2, reaction_s
    s_min = psi.s_min[:, None]
    v_f, v_l = gaps.v_f.gather(1, choice), gaps.v_l.gather(1, choice)
    room_f = 2.0 * b * (a - s_min - gaps.extra_new.gather(1, choice)).clamp(min=0.0)
    ex_l = gaps.extra_l.gather(1, choice)
    room_l = 2.0 * b * (gaps.length.gather(1, choice) - a - s_min - ex_l).clamp(min=0.0)
    need = torch.sqrt((v_f * v_f + 2.0 * b * tau * v_f - room_f).clamp(min=0.0))
    cap = torch.sqrt(b * b * tau * tau + v_l * v_l + room_l) - b * tau
    lo = torch.where(gaps.has_f.gather(1, choice), need, 0.0)
    hi = torch.where(gaps.has_l.gather(1, choice), cap, math.inf)
    if stops is not None and road is not None:
        arc = road.wrap(gaps.start.gather(1, choice) + a)
        d = stop_room_m(gaps.lane.gather(1, choice), arc, stops, road)
        room_s = 2.0 * b * (d - s_min).clamp(min=0.0)  # as safe_speeds: a standing leader
        hi = torch.minimum(hi, torch.sqrt(b * b * tau * tau + room_s) - b * tau)
    return torch.maximum(lo, psi.v_min[:, None]), torch.minimum(hi, psi.v_max[:, None])


@torch.no_grad()
@one_thread()
def complete_section(
    net: SectionGeneratorNet,
    section: Section,
    snaps: SectionSnapshots,
    k: np.ndarray,
    t_max: int,
    seed: int,
    brake_mps2: float | None = None,
    reaction_s: float = 0.0,
    generated_length_m: float | None = None,
) -> SectionCompletion:
    """Algorithm 3 on a section, batched over snapshots: ``k[s]`` hidden vehicles for
    snapshot s, each from up to ``t_max`` trials, projection as the counted fallback.

    With ``brake_mps2`` (the scenario's braking bound), generated speeds are then made
    kinematically consistent with their lane neighbours (``safe_speeds``, with a reaction
    time of ``reaction_s``). ``generated_length_m``: the generated vehicles' length in the
    environment (``env.section_bank.typical_length``; None: the snapshots' shortest). Where
    it is longer, each generated vehicle is placed with that much more room behind it and
    keeps it ahead of the next (``generated_extra``), as an observed truck does: the scene
    is admissible for the vehicles SUMO inserts. Inference alone: a net trained without it
    (its rollouts at psi's s_min) completes with it. The pair check's extra stays the
    junction's (``junction_extra``; a standing follower may stand closer)."""
    kin = None if brake_mps2 is None else (float(brake_mps2), float(reaction_s))
    t0 = time.perf_counter()
    road = Road.of(section)
    gen = torch.Generator().manual_seed(int(seed))
    scene = Scene.start(snaps, k, road)
    scene.new_extra = generated_extra(snaps, generated_length_m)
    if scene.new_extra > 0.0:  # the generated slots' length, once placed (observe's extra)
        scene.extra[:, scene.n_obs_slots :] = scene.new_extra
    psi = Psi.of(snaps.psi)
    b = len(snaps)
    stop_pts = scene_stops(section, snaps)  # standing obstacles: red lights, lane ends
    stops = None  # the same as tensors, (B, P) lane and arc (inf: none)
    if stop_pts is not None:  # on the generator's lane numbers (``section_lanes``)
        at_lane = road.lane_numbers(stop_pts[0], np.nan_to_num(stop_pts[1]))
        stops = (
            torch.as_tensor(at_lane, dtype=torch.int64),
            torch.as_tensor(np.nan_to_num(stop_pts[1], nan=np.inf), dtype=torch.float64),
        )
    trials = np.zeros(b, dtype=np.int64)
    projections = np.zeros(b, dtype=np.int64)
    dropped = np.zeros(b, dtype=np.int64)
    for step in range(int(scene.k.max()) if b else 0):
        idx = torch.nonzero(scene.k > step).flatten()
        sub = psi.take(idx)
        obs = scene.observe(step, idx, sub, road, gen)
        m = scene.n_obs_slots + step
        bounded = bounded_gaps(
            obs.gaps,
            scene.lane[idx, :m],
            scene.arc[idx, :m],
            scene.present[idx, :m],
            scene.k[idx] - step,
            sub,
            road,
            scene.n_obs_slots,
        )
        if bounded is not None:  # psi's spacing bounds: gaps with no accepted part are out
            fits = bounded.valid & (bounded.room > 0)
            obs.choosable = obs.choosable & (fits | ~(fits & obs.choosable).any(1, keepdim=True))
        t = propose(net, obs, sub, road, t_max, gen)
        g = obs.gaps if bounded is None else bounded
        a = t.arc - g.start.gather(1, t.choice)
        if road.closed:
            a = torch.remainder(a, road.length_m)
        ok = (
            obs.choosable.gather(1, t.choice)
            & (g.room.gather(1, t.choice) >= 0)
            & (a >= g.lo.gather(1, t.choice) - TOL_M)
            & (a <= g.hi.gather(1, t.choice) + TOL_M)
            & road.has_lane(t.lane, t.arc)
            & (t.speed >= sub.v_min[:, None])
            & (t.speed <= sub.v_max[:, None])
        )
        if kin is not None:
            at = None if stops is None else (stops[0][idx], stops[1][idx])
            v_lo, v_hi = kinematic_speeds(g, t.choice, a, sub, *kin, at, road)
            ok &= v_lo <= v_hi
            t.speed = torch.where(ok, torch.minimum(torch.maximum(t.speed, v_lo), v_hi), t.speed)
        any_ok = ok.any(dim=1)
        rows = torch.arange(len(idx))
        pick = torch.where(any_ok, ok.double().argmax(dim=1), t_max - 1)
        lane, arc, v = t.lane[rows, pick], t.arc[rows, pick].clone(), t.speed[rows, pick]
        idx_np = idx.numpy()
        trials[idx_np] += pick.numpy() + 1
        failed = np.flatnonzero(~any_ok.numpy())
        fits = torch.ones(len(idx), dtype=torch.bool)
        if len(failed):
            choice = t.choice[rows, pick]
            for r in failed:
                window = None
                if kin is not None:
                    window = partial(_window_of, g, sub, int(r), kin, at, road)
                x, j = _project(road, g, t.probs, int(r), int(choice[r]), float(arc[r]), window)
                arc[r] = x
                fits[r] = j >= 0
                if j >= 0:  # the gap it went to may be on another lane than the trial's
                    lane[r] = g.lane[r, j]
                if window is not None and j >= 0:  # its speed into the window where it is
                    off = x - float(g.start[r, j])
                    off = float(np.mod(off, road.length_m)) if road.closed else off
                    w_lo, w_hi = window(j, torch.tensor([off], dtype=torch.float64))
                    v[r] = min(
                        max(float(v[r]), float(w_lo[0])), max(float(w_lo[0]), float(w_hi[0]))
                    )
            projections[idx_np[failed]] += 1
            dropped[idx_np] += (~fits).numpy()
        v = torch.minimum(torch.maximum(v, sub.v_min), sub.v_max)
        scene.place(step, idx, lane, arc, v, fits)
    comp = _unpack(scene, snaps, road, trials, projections, time.perf_counter() - t0)
    comp.dropped = dropped
    if brake_mps2 is not None:
        obs = np.asarray(snaps.valid & snaps.observed, dtype=bool)
        extra = np.where(obs, extra_lengths(snaps), 0.0)
        # psi's smallest spacing is the shortest vehicle's: a generated 5 m car placed there
        # in a junction left a moving follower less than its minGap in SUMO, whose link then
        # stopped that car at the junction and the car behind ran into it (fresh 1169, stop
        # 46). On a lane SUMO's car-following brakes such a follower: there psi's spacing
        # holds, as before (applied everywhere it dropped 3-8% of the generated vehicles).
        extra = np.concatenate([extra, junction_extra(section, snaps, comp, generated_length_m)], 1)
        stand = snaps.psi[:, PSI_INDEX["spacing_min_m"]]
        safe_speeds(comp, section, stand, brake_mps2, reaction_s, extra, stop_pts)
        args = (section, stand, brake_mps2, reaction_s, extra, stop_pts)
        comp.dropped = dropped + drop_unsafe_pairs(comp, *args)
    return comp


def junction_extra(
    section: Section, snaps: SectionSnapshots, comp: SectionCompletion, length_m: float | None
) -> np.ndarray:
    """(S, K_max) the generated vehicles' length beyond the snapshots' shortest where they
    stand in a junction, else 0 (``complete_section``'s ``generated_length_m``)."""
    arc = comp.arc_m[:, snaps.arc_m.shape[1] :]
    shortest = shortest_length(snaps)
    if length_m is None or length_m <= shortest:
        return np.zeros_like(arc)
    s = section.wrap(np.where(np.isfinite(arc), arc, 0.0).ravel())
    inside = (section.node_of(s)[0] != section.edge_index(s)).reshape(arc.shape)
    return np.where(inside, length_m - shortest, 0.0)


def _unpack(
    scene: Scene,
    snaps: SectionSnapshots,
    road: Road,
    trials: np.ndarray,
    projections: np.ndarray,
    wall_s: float,
) -> SectionCompletion:
    """The completed scenes in the output layout: observed vehicles back in their snapshot
    slots (bit for bit), the generated ones after them, on SUMO's lane indices."""
    b, n = snaps.arc_m.shape
    m = scene.n_obs_slots
    obs = np.asarray(snaps.valid & snaps.observed, dtype=bool)
    gen = scene.present[:, m:].numpy()
    lane = road.sumo_lanes(scene.lane[:, m:].numpy(), scene.arc[:, m:].numpy())
    return SectionCompletion(
        lane=np.concatenate([np.where(obs, snaps.lane, 0), np.where(gen, lane, 0)], 1),
        arc_m=np.concatenate(
            [np.where(obs, snaps.arc_m, 0.0), np.where(gen, scene.arc[:, m:], 0.0)], 1
        ),
        speed_mps=np.concatenate(
            [np.where(obs, snaps.speed_mps, 0.0), np.where(gen, scene.speed[:, m:], 0.0)], 1
        ),
        valid=np.concatenate([obs, gen], 1),
        generated=np.concatenate([np.zeros_like(obs), gen], 1),
        trials=trials,
        projections=projections,
        wall_s=wall_s,
    )


def uniform_completion(
    net: SectionGeneratorNet | None,
    section: Section,
    snaps: SectionSnapshots,
    k: np.ndarray,
    t_max: int,
    seed: int,
) -> SectionCompletion:
    """Baseline: hidden vehicles at uniform positions on the section, a lane drawn uniformly
    among those that exist there, at psi's mean speed (no bounds checked; ``net`` and
    ``t_max`` are unused: the signature is ``complete_section``'s)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng([int(seed), 303])
    b, n = snaps.arc_m.shape
    k = np.maximum(np.asarray(k, dtype=np.int64), 0)
    k_max = int(k.max()) if b else 0
    gen_mask = np.arange(k_max)[None, :] < k[:, None]
    arc = rng.uniform(0.0, section.length_m, (b, k_max))
    # among the lane indices that exist there (in a junction: those it leads to)
    road = Road.of(section)
    there = road.has_lane(torch.arange(road.max_lanes), torch.as_tensor(arc)[..., None]).numpy()
    nth = np.floor(rng.random((b, k_max)) * there.sum(axis=-1))[..., None]
    lane = road.sumo_lanes((np.cumsum(there, axis=-1) <= nth).sum(axis=-1), arc)
    obs = snaps.valid & snaps.observed
    v_mean = snaps.psi[:, PSI_INDEX["mean_speed_mps"]]
    return SectionCompletion(
        lane=np.concatenate([np.where(obs, snaps.lane, 0), np.where(gen_mask, lane, 0)], 1),
        arc_m=np.concatenate([np.where(obs, snaps.arc_m, 0.0), np.where(gen_mask, arc, 0.0)], 1),
        speed_mps=np.concatenate(
            [np.where(obs, snaps.speed_mps, 0.0), np.where(gen_mask, v_mean[:, None], 0.0)], 1
        ),
        valid=np.concatenate([obs, gen_mask], 1),
        generated=np.concatenate([np.zeros_like(obs), gen_mask], 1),
        trials=np.zeros(b, dtype=np.int64),
        projections=np.zeros(b, dtype=np.int64),
        wall_s=time.perf_counter() - t0,
    )

"""What B scenes of a one-lane loop observe and earn, as numpy over (B, N) slot arrays;
what a step of the batched core returns, and which sections it takes.

The batched env core's (``env/batched.py``) twins of ``section_observations`` and
``section_macro_reward`` for the case it takes (a closed one-lane section: the ring): the
same leaders, observation features and reward terms, with the same float operations where
the single-scene functions have them (a test compares them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macromicro_sumo.data.objective import macro_reward, macro_terms
from macromicro_sumo.env.section_bank import section_target
from macromicro_sumo.env.section_replay import junction_vias
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section


@dataclass(frozen=True)
class BatchStep:
    """What one step of ``BatchedSectionCore`` returns, per scene (B, ...)."""

    obs: np.ndarray  # (B, N, d); a scene reset in this step: its start observation
    r_macro: np.ndarray  # (B,) 0 for scenes reset in this step or idle
    terms: dict[str, np.ndarray]  # (B,) named reward terms
    collision: np.ndarray  # (B,) bool
    truncated: np.ndarray  # (B,) bool: ended early (an error, no vehicle left)
    stepped: np.ndarray  # (B,) bool: scenes that took an env step (resets and idle: not)
    was_reset: np.ndarray  # (B,) bool: scenes (re)started in this step
    active: np.ndarray  # (B, N) bool
    errors: tuple[str, ...]  # per scene, "" for none


def check_batchable(section: Section, net_has_lights: bool = False) -> None:
    """One-line error where ``BatchedSectionCore`` does not apply (``SectionCore`` does)."""
    ok = section.closed and section.max_lanes == 1 and bool(section.links.all())
    if not ok or junction_vias(section) or net_has_lights:
        raise UserError(
            "env.batched: the batched core takes closed one-lane sections without signals "
            "or junction-internal lanes (a ring); use SectionCore (num_envs = 1) for this one"
        )


def loop_leaders(
    arc_m: np.ndarray, active: np.ndarray, length_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Leader (-1: inactive) and front-to-front spacing [m] of every slot, per row: the next
    active vehicle round the loop (``loop_successors`` of each row's active slots: equal
    positions keep their slot order; a lone vehicle follows itself a lap ahead)."""
    b, n = arc_m.shape
    s = np.mod(arc_m, length_m)
    order = np.argsort(np.where(active, s, np.inf), axis=1, kind="stable")
    k = active.sum(axis=1, keepdims=True)
    j = np.arange(n)[None, :]
    nj = np.where(j + 1 < k, j + 1, 0)
    s_sorted = np.take_along_axis(s, order, axis=1)
    s_next = np.take_along_axis(s_sorted, nj, axis=1)
    # loop_successors' own float operations: the last one's gap is first + L - last
    gap_sorted = np.where(nj == 0, s_next + length_m - s_sorted, s_next - s_sorted)
    leader = np.full((b, n), -1, dtype=np.int64)
    spacing = np.full((b, n), NO_LEADER_GAP_M)
    rows = np.arange(b)[:, None]
    in_scene = j < k
    leader[rows, order] = np.where(in_scene, np.take_along_axis(order, nj, axis=1), -1)
    spacing[rows, order] = np.where(in_scene, gap_sorted, NO_LEADER_GAP_M)
    return leader, spacing


def loop_observations(
    section: Section,
    limits_mps: np.ndarray,
    arc_m: np.ndarray,
    speed_mps: np.ndarray,
    active: np.ndarray,
    obs_dim: int,
    factor: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations (B, N, obs_dim), leaders and spacings of B scenes on a one-lane loop
    (``section_observations``' features: speed, limit, spacing, v - v_leader, and with 6
    features the next edge's limit and the distance to it); ``limits_mps`` (B, E, lanes):
    each scene's limits; ``factor`` (B, N): each driver's desired-speed factor (None: 1).
    Inactive slots are zeros."""
    b = arc_m.shape[0]
    length = section.length_m
    leader, spacing = loop_leaders(arc_m, active, length)
    rows = np.arange(b)[:, None]
    e = section.edge_index(arc_m)
    obs = np.zeros((*arc_m.shape, obs_dim))
    v = speed_mps
    obs[..., 0] = v
    obs[..., 1] = limits_mps[rows, e, 0]
    near = spacing < NO_LEADER_GAP_M  # beyond: no leader, as ``section_observations``
    obs[..., 2] = np.where(near, spacing, NO_LEADER_GAP_M)
    obs[..., 3] = np.where(near, v - np.take_along_axis(v, np.maximum(leader, 0), axis=1), 0.0)
    if obs_dim > 4:
        nxt = (e + 1) % len(section.edge_ids)
        obs[..., 4] = limits_mps[rows, nxt, 0]
        s = np.mod(arc_m, length)
        obs[..., 5] = section.offsets_m[nxt] + np.where(nxt == 0, length, 0.0) - s
    if factor is not None:
        obs[..., 1] *= factor
        if obs_dim > 4:
            obs[..., 4] *= factor
    return np.where(active[..., None], obs, 0.0), leader, spacing


def batch_macro_reward(
    speed_mps: np.ndarray,
    spacing_m: np.ndarray,
    leader: np.ndarray,
    hidden: np.ndarray,
    active: np.ndarray,
    psi: np.ndarray,
    lambda_v: float,
    lambda_d: float,
    speed_scale_mps: float = 0.0,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """r_macro (B,) and its named terms (B,) of B scenes against their psi (B, fields):
    ``section_macro_reward`` with masks instead of selections (A: the spacings of active
    vehicles with a leader that touch a hidden vehicle, it or its leader)."""
    lead = np.maximum(leader, 0)
    in_a = active & (leader >= 0) & (hidden | np.take_along_axis(hidden, lead, axis=1))
    terms = macro_terms(speed_mps, active, spacing_m, in_a, section_target(psi.T), speed_scale_mps)
    return macro_reward(terms, lambda_v, lambda_d), terms

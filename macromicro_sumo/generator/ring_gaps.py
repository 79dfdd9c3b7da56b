"""The ring generator's scene: gaps in arc order, Psi as named arrays, array helpers.

The scene is a set of vehicles on the ring. Each autoregressive step of the generator
(``ring_model``) looks at the gaps of the current scene (observed vehicles plus those
generated so far), sorted by angle, so the model does not depend on the order or labels
of vehicles and the ring has no start. With no vehicle present (K = N) the first vehicle
goes anywhere (rotation symmetry): its gap is the whole ring from a random angle.

Geometry and features are one definition for torch (training, with gradients) and numpy
(inference, float64 geometry): ``array_module`` picks the backend of an array, and
``take``, ``row_index``, ``clip`` and ``stack_last`` hide the calls where the two differ.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import torch

from macromicro_sumo.data.ring import Snapshots


def array_module(x: Any) -> Any:
    """The array module of ``x``: geometry and features run on torch (training, with
    gradients) and numpy (inference) from one definition."""
    return torch if isinstance(x, torch.Tensor) else np


def take(x: Any, idx: Any) -> Any:
    """x[b, idx[b, i]] along axis 1 (numpy: trailing axes of x are kept)."""
    if isinstance(x, torch.Tensor):
        return x.gather(1, idx)
    return x[row_index(len(x)), idx]


@functools.lru_cache(maxsize=32)
def row_index(b: int, ndim: int = 2) -> np.ndarray:
    """np.arange(b) shaped (B, 1, ...) with ``ndim`` axes, for fancy indexing."""
    return np.arange(b).reshape(b, *[1] * (ndim - 1))


def clip(x: Any, lo: Any = None, hi: Any = None) -> Any:
    """torch.clamp / np.clip without the latter's per-call overhead."""
    if isinstance(x, torch.Tensor):
        return torch.clamp(x, lo, hi)
    if lo is not None:
        x = np.maximum(x, lo)
    return x if hi is None else np.minimum(x, hi)


def stack_last(xs: list[Any]) -> Any:
    """Stack along a new last axis."""
    if isinstance(xs[0], torch.Tensor):
        return torch.stack(xs, -1)
    a = np.array(xs, dtype=np.float64)  # the arrays must have the same shape
    return a.transpose(*range(1, a.ndim), 0)


# --------------------------------------------------------------------------- scene geometry


def ring_gaps(arc: Any, present: Any, length_m: float) -> tuple[Any, ...]:
    """Gaps of the present vehicles in arc order, batched over rows (torch or numpy).

    Returns (follower slot, leader slot, gap [m], valid) each (B, N): position i holds
    the i-th gap in arc order; positions >= the number of present vehicles are invalid.
    A lone vehicle's gap is the whole ring.
    """
    xp = array_module(arc)
    n = arc.shape[1]
    order = xp.argsort(xp.where(present, arc, arc + 4 * length_m), 1)
    m = present.sum(1)[:, None]
    idx = xp.arange(n)
    follower = order
    leader = take(order, xp.where(idx + 1 < m, idx + 1, 0))
    gap = (take(arc, leader) - take(arc, follower)) % length_m
    gap = xp.where(follower == leader, length_m, gap)
    return follower, leader, gap, idx < m


@dataclass(frozen=True)
class PsiTensors:
    """Psi split into named (B,) arrays (torch or numpy), plus the scales features use."""

    v_mean: Any
    d_mean: Any
    d_min: Any
    d_max: Any
    v_min: Any
    v_max: Any
    d_std: Any = None  # measured spacing std [m] (spacing_dispersion = "measured")

    @classmethod
    def from_array(
        cls,
        psi: np.ndarray | torch.Tensor,
        dtype: torch.dtype = torch.float32,
        d_std: np.ndarray | None = None,
    ) -> PsiTensors:
        p = torch.as_tensor(psi, dtype=dtype)
        return cls(
            *p.unbind(dim=1), d_std=None if d_std is None else torch.as_tensor(d_std, dtype=dtype)
        )

    @classmethod
    def of(cls, snaps: Snapshots, dtype: torch.dtype = torch.float32) -> PsiTensors:
        """Psi of a batch of snapshots, with the dispersion target when they carry one."""
        return cls.from_array(snaps.psi, dtype, snaps.spacing_std_m)

    @classmethod
    def arrays(cls, snaps: Snapshots) -> PsiTensors:
        """The same as float64 numpy arrays (inference)."""
        d_std = snaps.spacing_std_m
        return cls(
            *np.asarray(snaps.psi, dtype=np.float64).T,
            d_std=None if d_std is None else np.asarray(d_std, dtype=np.float64),
        )

    @cached_property
    def v_range(self) -> Any:
        return self.v_max - self.v_min

    @cached_property
    def v_scale(self) -> Any:
        return clip(0.5 * (self.v_max - self.v_min), 0.1)

    @cached_property
    def static_features(self) -> list[Any]:
        """The 5 global features (B,) each that depend on Psi alone (computed once):
        d_min, d_max relative to the mean spacing, then the speed range and centre, and the
        dispersion target (0 unless spacing_dispersion = "measured")."""
        xp = array_module(self.d_mean)
        d_std = xp.zeros_like(self.d_mean) if self.d_std is None else self.d_std
        return [
            self.d_min / self.d_mean,
            self.d_max / self.d_mean,
            (self.v_max - self.v_min) / self.v_mean,
            (self.v_min + self.v_max - 2 * self.v_mean) / (2 * self.v_scale),
            d_std / self.d_mean,
        ]

    @cached_property
    def columns(self) -> tuple[Any, ...]:
        """(v_scale, v_mean, d_mean, d_min, d_max) as (B, 1) columns (computed once)."""
        return tuple(
            x[:, None] for x in (self.v_scale, self.v_mean, self.d_mean, self.d_min, self.d_max)
        )


def scene_gaps(arc: Any, present: Any, length_m: float, anchor: Any) -> tuple[Any, ...]:
    """``ring_gaps`` of a scene, plus each gap's start [m] (B, N).

    An empty ring gets one virtual vehicle at ``anchor`` (a random angle) whose gap is the
    whole ring, so the first vehicle of a scene goes anywhere (rotation symmetry).
    """
    xp = array_module(arc)
    empty = ~present.any(1)
    # numpy skips it when no ring is empty; torch always takes it, so that the autograd
    # graph, and with it training, stays the same to the last bit.
    if xp is torch or empty.any():
        virtual = empty[:, None] & (xp.arange(arc.shape[1]) == 0)
        arc, present = xp.where(virtual, anchor[:, None], arc), present | virtual
    follower, leader, gap, valid = ring_gaps(arc, present, length_m)
    return follower, leader, gap, valid, take(arc, follower)

"""The macro objective: one definition of the paper's loss terms, for every stage and road.

Stage I trains the generator on ``macro_loss`` of completed scenes; Stage II rewards the
policy with ``macro_reward`` of the scene it drives. Both come from ``macro_terms``, a
linear combination of named terms (as HighwayEnv's reward terms or Waymax's metrics):

* ``L_speed`` = ((v_mean - v_target) / s)^2 over every vehicle on the road; s = v_target
  (the paper's relative error) or a fixed scale in m/s (``policy.macro_speed_scale_mps``);
* ``L_vstd`` = |std(v) - the detectors' speed std| / v_target, only where a target is
  given: the speed spread that Psi's other fields say nothing about;
* over the spacings in A (the gaps a generated or driven vehicle touches, chosen by the
  caller): ``L_mean`` = (mean_A(d) / d_target - 1)^2; ``L_min`` and ``L_max`` = mean_A of
  the squared relative shortfall under d_min and excess over d_max (inf: no upper bound);
* ``L_var``, the dispersion: the paper's std_A(d) / d_target, or, where the detectors
  measured a spacing std sigma, |mean_A (d - d_target)^2 - sigma^2| / d_target^2 (deviations
  from the measured mean, variances not stds: see docs/design.md, "Why the dispersion").

loss = lambda_v (L_speed + L_vstd) + lambda_d (L_mean + L_min + L_max + L_var);
reward = 1 / (1 + loss). Arrays are batched over leading axes and reduced over the last one;
numpy and torch alike (the generator's gradients flow through the same expressions).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


@dataclass(frozen=True)
class MacroTarget:
    """What the terms compare with: Psi's fields, scalars for one scene or (B,) arrays.

    Attributes:
        mean_speed_mps: space-mean speed v_target [m/s].
        mean_spacing_m: mean front-to-front spacing d_target [m].
        spacing_min_m: smallest admissible spacing d_min [m].
        spacing_max_m: largest admissible spacing d_max [m]; inf where there is none.
        spacing_std_m: measured spacing std [m] for the measured dispersion; None for the
            paper's; NaN entries fall back to the paper's.
        speed_std_mps: measured speed std [m/s] for ``L_vstd``; None (or NaN): no term.
        spacing_center_m: the mean spacing [m] the measured dispersion counts deviations
            from; None: ``mean_spacing_m`` (a closed section's generator passes its scene's
            exact mean, see ``generator.dispersion_center``).
    """

    mean_speed_mps: Any
    mean_spacing_m: Any
    spacing_min_m: Any
    spacing_max_m: Any
    spacing_std_m: Any = None
    speed_std_mps: Any = None
    spacing_center_m: Any = None


def _sqrt(x: Any) -> Any:
    return torch.sqrt(x) if isinstance(x, torch.Tensor) else np.sqrt(x)


def _relu(x: Any) -> Any:
    return torch.relu(x) if isinstance(x, torch.Tensor) else np.maximum(x, 0.0)


def _at_least_one(x: Any) -> Any:
    return x.clamp(min=1.0) if isinstance(x, torch.Tensor) else np.maximum(x, 1.0)


def _where(cond: Any, a: Any, b: Any) -> Any:
    return torch.where(cond, a, b) if isinstance(cond, torch.Tensor) else np.where(cond, a, b)


def _all_finite(x: Any) -> bool:
    return (
        bool(torch.isfinite(x).all()) if isinstance(x, torch.Tensor) else bool(np.isfinite(x).all())
    )


def _counted(mask: Any, values: Any) -> tuple[Any, Any, Any]:
    """(values with the uncounted ones zeroed, count >= 1, any counted) over the last axis.

    ``mask`` None counts every value: what a caller passes that has already selected them
    (one scene in the env's hot path, where the masks' extra reductions would cost more
    than the terms themselves)."""
    if mask is None:
        n = values.shape[-1]
        return values, max(n, 1), n > 0
    n = mask.sum(-1)
    return values * mask, _at_least_one(n), n > 0


def macro_terms(
    speed_mps: Any,
    on_road: Any,
    spacing_m: Any,
    in_a: Any,
    target: MacroTarget,
    speed_scale_mps: float = 0.0,
    eps: float = 0.0,
) -> dict[str, Any]:
    """The named terms of scenes: ``speed_mps`` / ``on_road`` and ``spacing_m`` / ``in_a``
    are (..., N) values and 0/1 masks (the vehicles counted, the spacings in A; None: all).

    ``eps`` is added under square roots (their slope is infinite at 0: with eps, equal
    gaps or speeds stay trainable). Scenes with an empty A get zero spacing terms.
    """
    return {
        **speed_terms(speed_mps, on_road, target, speed_scale_mps, eps),
        **spacing_terms(spacing_m, in_a, target, eps),
    }


def speed_terms(
    speed_mps: Any,
    on_road: Any,
    target: MacroTarget,
    speed_scale_mps: float = 0.0,
    eps: float = 0.0,
) -> dict[str, Any]:
    """``L_speed`` and ``L_vstd`` of (..., N) speeds, counting the vehicles in ``on_road``."""
    counted, n, _ = _counted(on_road, speed_mps)
    v_mean = counted.sum(-1) / n
    v_t = target.mean_speed_mps
    if speed_scale_mps > 0:
        terms = {"L_speed": ((v_mean - v_t) / speed_scale_mps) ** 2}
    else:  # the paper's relative error
        terms = {"L_speed": (v_mean / v_t - 1.0) ** 2}
    sigma = target.speed_std_mps
    if sigma is not None:  # no target, no term
        dev, _, _ = _counted(on_road, speed_mps - v_mean[..., None])
        v_std = _sqrt((dev * dev).sum(-1) / n + eps)
        known = sigma == sigma  # NaN: no target
        gap = v_std - _where(known, sigma, 0.0)
        terms["L_vstd"] = known * _sqrt(gap * gap + eps) / v_t
    return terms


def spacing_terms(
    spacing_m: Any, in_a: Any, target: MacroTarget, eps: float = 0.0
) -> dict[str, Any]:
    """``L_mean``, ``L_min``, ``L_max`` and ``L_var`` of (..., N) spacings over A (``in_a``)."""
    counted, cnt, has = _counted(in_a, spacing_m)
    d_t, d_min, d_max = target.mean_spacing_m, target.spacing_min_m, target.spacing_max_m
    mean = counted.sum(-1) / cnt
    low, _, _ = _counted(in_a, _relu(d_min[..., None] - spacing_m) / d_min[..., None])
    high, _, _ = _counted(in_a, _relu(spacing_m - d_max[..., None]) / d_max[..., None])
    sigma = target.spacing_std_m
    measured_only = sigma is not None and _all_finite(sigma)
    if not measured_only:  # the paper's dispersion, around A's own mean
        dev, _, _ = _counted(in_a, spacing_m - mean[..., None])
        own = _sqrt((dev * dev).sum(-1) / cnt + eps) / d_t
    if sigma is None:
        l_var = own
    else:  # the measured dispersion, around the measured mean
        center = d_t if target.spacing_center_m is None else target.spacing_center_m
        dev, _, _ = _counted(in_a, spacing_m - center[..., None])
        measured = abs((dev * dev).sum(-1) / cnt - sigma * sigma) / (d_t * d_t)
        l_var = measured if measured_only else _where(sigma == sigma, measured, own)
    return {
        "L_mean": has * (mean / d_t - 1.0) ** 2,
        "L_min": (low * low).sum(-1) / cnt,
        "L_max": (high * high).sum(-1) / cnt,
        "L_var": has * l_var,
    }


def macro_loss(terms: dict[str, Any], lambda_v: float, lambda_d: float) -> Any:
    """lambda_v (L_speed + L_vstd) + lambda_d (L_mean + L_min + L_max + L_var)."""
    speed = terms["L_speed"] + terms.get("L_vstd", 0.0)
    spacing = terms["L_mean"] + terms["L_min"] + terms["L_max"] + terms["L_var"]
    return lambda_v * speed + lambda_d * spacing


def macro_reward(terms: dict[str, Any], lambda_v: float, lambda_d: float) -> Any:
    """r_macro = 1 / (1 + loss): in (0, 1], 1 when the scene matches Psi."""
    return 1.0 / (1.0 + macro_loss(terms, lambda_v, lambda_d))

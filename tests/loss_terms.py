"""The paper's loss terms as positional arrays, for tests: thin wrappers of
``data.objective`` (the one definition of the macro objective)."""

from __future__ import annotations

import numpy as np

from macromicro_sumo.data.objective import MacroTarget, spacing_terms, speed_terms


def spacing_losses(
    gaps_m: np.ndarray,
    mask: np.ndarray,
    mean_target_m: np.ndarray,
    d_min_m: np.ndarray,
    d_max_m: np.ndarray,
    target_std_m: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The paper's L_mean, L_min, L_max, L_var over the gaps in ``mask`` (the set A), (B,)
    each: ``objective.spacing_terms`` with Psi's fields as positional arrays."""
    target = MacroTarget(np.nan, mean_target_m, d_min_m, d_max_m, target_std_m)
    return spacing_terms(gaps_m, mask.astype(float), target)


def speed_loss(
    speeds_mps: np.ndarray, target_mps: np.ndarray, scale_mps: float = 0.0
) -> np.ndarray:
    """L_speed of (B, N) fleets (every vehicle counted): ``objective.speed_terms``."""
    target = MacroTarget(target_mps, np.nan, np.nan, np.nan)
    return speed_terms(speeds_mps, np.ones_like(speeds_mps), target, scale_mps)["L_speed"]

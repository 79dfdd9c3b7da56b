"""The observation features of a hidden vehicle: name, unit, and a fixed normalisation.

``FEATURES`` has one entry per feature that ``physics.OBSERVATION_FEATURES`` can list; its
shift and scale bring the SI value to O(1) on the paper's ring (speeds near 12 m/s, limits
12-14 m/s, spacings near 125 m). The ring's PPO agent (``policy.agent``) normalises with them,
and so do the public environments with ``normalize=True``. On a section of a user's network
the speeds and spacings are another road's: there the shift and scale are the mean and std
of the bank's initial observations (``bank_shift_scale``), as the section's PPO agent has.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macromicro_sumo.road.physics import OBSERVATION_FEATURES


@dataclass(frozen=True)
class Feature:
    name: str
    unit: str
    shift: float  # normalised = (value - shift) / scale
    scale: float
    doc: str


FEATURES = {
    f.name: f
    for f in (
        Feature("speed_mps", "m/s", 12.0, 2.0, "own speed"),
        Feature("speed_limit_mps", "m/s", 13.0, 1.0, "speed limit where the vehicle is"),
        Feature("spacing_m", "m", 125.0, 50.0, "front-to-front spacing to the leader"),
        # The spacing's scale, its shift one 5 m car less: a fleet of 5 m cars normalises
        # its gaps as "lookahead" its spacings.
        Feature("gap_m", "m", 120.0, 50.0, "bumper-to-bumper gap to the leader (its length)"),
        Feature("delta_v_mps", "m/s", 0.0, 1.0, "own speed minus the leader's"),
        Feature("next_limit_mps", "m/s", 13.0, 1.0, "speed limit of the next edge"),
        Feature("dist_to_next_m", "m", 80.0, 50.0, "distance to the next edge"),
        Feature("length_m", "m", 5.0, 3.0, "own vehicle length (its vType's)"),
    )
}


def shift_scale(observation: str) -> tuple[np.ndarray, np.ndarray]:
    """The fixed (shift, scale) of ``policy.observation``'s features, in feature order."""
    names = OBSERVATION_FEATURES[observation]
    return (
        np.array([FEATURES[n].shift for n in names]),
        np.array([FEATURES[n].scale for n in names]),
    )


def bank_shift_scale(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-feature mean and std of observations ``obs`` (V, D); a constant feature gets
    scale 1 (the section PPO agent's normalisation)."""
    if len(obs) == 0:
        return np.zeros(obs.shape[1]), np.ones(obs.shape[1])
    shift, scale = obs.mean(axis=0), obs.std(axis=0)
    return shift, np.where(scale > 1e-6, scale, 1.0)


@dataclass
class StepResult:
    """What one step of an env core (``env.section.SectionCore``) returns."""

    obs: np.ndarray  # (N, d) every slot's observation
    r_macro: float
    terms: dict[str, float]
    collision: bool
    truncated: bool
    error: str
    active: np.ndarray  # (N,) bool: slots on the road after this step

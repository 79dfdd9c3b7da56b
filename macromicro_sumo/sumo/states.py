"""What the SUMO boundary (``sumo.simulation``) hands the rest of the package: the vehicle
states read once a step, the signal states a driver stops for, and SUMO's speed and
lane-change mode bits. Plain values, no libsumo: readers need not start SUMO."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

# Signal states a driver treats as a standing leader at the stop line (red, yellow, red-yellow).
STOP_STATES = frozenset("rRyYu")

# SUMO's speed mode (TraCI setSpeedMode) bits: 1 safe speed, 2 max accel, 4 max decel, 8
# right of way at junctions, 16 brake for red lights, 32 disregard right of way inside a
# junction. 31 is SUMO's default.
DEFAULT_SPEED_MODE = 31
DEFAULT_LANE_CHANGE_MODE = 0b011001010101  # SUMO's default lane-change mode (1621)


@dataclass(frozen=True)
class VehicleStates:
    """Every vehicle on the road (not teleporting) after a step, in SUMO's order: sorted
    by ID (its vehicle dictionary is a std::map); row i for ``ids[i]``."""

    ids: tuple[str, ...]
    lanes: list[str]
    pos_m: np.ndarray  # position on its lane [m]
    speed_mps: np.ndarray
    accel_mps2: np.ndarray

    @cached_property
    def index(self) -> dict[str, int]:
        """Vehicle ID -> row."""
        return dict(zip(self.ids, range(len(self.ids)), strict=True))

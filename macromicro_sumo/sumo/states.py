"""What the SUMO boundary (``sumo.simulation``) hands the rest of the package: the vehicle
states read once a step, the signal states a driver stops for, and SUMO's speed and
lane-change mode bits. Plain values, no libsumo: readers need not start SUMO."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

# Signal states a driver treats as a standing leader at the stop line (red, yellow, red-yellow).
STOP_STATES = frozenset("rRyYu")

# SUMO's speed mode (TraCI setSpeedMode) bits: 1 safe speed, 2 max accel, 4 max decel, 8
# right of way at junctions, 16 brake for red lights, 32 disregard right of way inside a
# junction. 31 is SUMO's default.
DEFAULT_SPEED_MODE = 31
DEFAULT_LANE_CHANGE_MODE = 0b011001010101  # SUMO's default lane-change mode (1621)


class _Once:
    """``functools.cached_property`` without its lock: the value computed at the first read
    and kept in the instance's ``__dict__``, which later reads find first (a non-data
    descriptor). Python 3.11's cached_property takes an RLock at that first read, ~1 us of
    a step (``VehicleStates.index``, read first by a deployment's driver every step); the
    state read is one thread's (3.12 dropped the lock)."""

    def __init__(self, func: Callable[[Any], Any]) -> None:
        self.func, self.name = func, func.__name__
        self.__doc__ = func.__doc__

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        value = obj.__dict__[self.name] = self.func(obj)
        return value


@dataclass(frozen=True)
class VehicleStates:
    """Every vehicle on the road (not teleporting) after a step, in SUMO's order: sorted
    by ID (its vehicle dictionary is a std::map); row i for ``ids[i]``."""

    ids: tuple[str, ...]
    lanes: list[str]
    pos_m: np.ndarray  # position on its lane [m]
    speed_mps: np.ndarray
    accel_mps2: np.ndarray

    @_Once
    def index(self) -> dict[str, int]:
        """Vehicle ID -> row."""
        return dict(zip(self.ids, range(len(self.ids)), strict=True))


# SUMO's jmStoplineGap where a vType sets none, for every carFollowModel [m].
SUMO_STOPLINE_GAP_M = 1.0


@dataclass(frozen=True)
class StopLines:
    """The next red or yellow stop line ahead of each vehicle (``Simulation.stop_lines``):
    SUMO's getNextTLS, the red link's lane and whether SUMO's driver stops at that line."""

    dist_m: np.ndarray  # front to the line; inf: no red or yellow ahead; NaN: no signal at all
    lanes: list[str]  # the red link's incoming lane, SUMO's own ("": none)
    # The link leaves the vehicle's lane (or the lanes it carries on to): SUMO's driver stops
    # before the line. False: its lane ends there (game/cross: a car routed through on 1si's
    # right-turn lane gets the through link's red); it stops at its lane's end, 0 m before.
    own: np.ndarray
    offset_m: np.ndarray  # the link lane's stopOffset for the vehicle's class (0: none)

    def stop_m(self, stopline_gap_m: float | np.ndarray = SUMO_STOPLINE_GAP_M) -> np.ndarray:
        """SUMO's gap to where its driver of a vType with jmStoplineGap ``stopline_gap_m``
        stands at the line: dist - max(jmStoplineGap, stopOffset), >= 0 (measured, SUMO
        1.28); inf where the link is not its own (its lane's end is its stop); NaN stays."""
        gap = np.maximum(stopline_gap_m, self.offset_m)
        return np.where(self.own, np.maximum(self.dist_m - gap, 0.0), np.inf + self.dist_m)

    def line_m(self, stopline_gap_m: float | np.ndarray = SUMO_STOPLINE_GAP_M) -> np.ndarray:
        """The line as a reader that stops ``stopline_gap_m`` (its vType's jmStoplineGap)
        before it takes it: ``stop_m`` + that gap, the stopOffset's excess moving it
        upstream; inf where not its own; NaN stays."""
        excess = np.maximum(self.offset_m - stopline_gap_m, 0.0)
        return np.where(self.own, self.dist_m - excess, np.inf + self.dist_m)

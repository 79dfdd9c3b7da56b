"""Per-vehicle values a speed-commanding driver keeps across steps (``deploy.drivers``), as
numpy arrays indexed by a stable slot per vehicle: one look-up of the slots per step, then
array indexing, instead of a dictionary look-up per vehicle and value (Bremen's
deployment: ~45 driven vehicles a step, where numpy's fixed cost per call and Python's per
vehicle were most of the driver's time, ``scripts/bench_deploy.py``).

What is kept per slot: the last step's speed command (``last_mps``, -inf: none, or none to
compare with), the vehicle's demand decel, maxSpeed, accel and length + minGap, its driver's desired-speed factor,
and two ``LaneCache``s of what SUMO was asked about the vehicle's lane (``lane_end``: where
it must have left its lane; ``dark``: no signal ahead on its route).
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.sumo.reads import codes

try:  # road/kernels.c, where setup.py built it (``LaneCache.due``)
    from macromicro_sumo.road import kernels
except ImportError:  # not built: numpy's form, the same indices
    kernels = None
# None where not built, or built before it had the pass (a stale build: numpy answers).
_lane_due = getattr(kernels, "lane_due", None)

NOT_ASKED = -1  # lane code of a cache entry that was never filled (or was dropped)
# No command (``VehicleSlots.commanded``'s write a step): a 0-d array, which numpy writes
# without converting a Python float each call (``deploy.observe._const``).
_NO_COMMAND = np.array(-np.inf)
_NO_COMMAND.flags.writeable = False


def _grown(old: np.ndarray, fill: float) -> np.ndarray:
    grown = np.full(2 * len(old), fill, dtype=old.dtype)
    grown[: len(old)] = old
    return grown


class LaneCache:
    """Per slot, a value SUMO gave about the vehicle's lane (one call per vehicle, too dear
    to ask every step), the lane it was asked on (a code) and the step from which it is
    asked again: due where not asked yet (lane ``NOT_ASKED``, step -inf), on another lane,
    or at that step, so that the check is one comparison of integer arrays a step."""

    def __init__(self, capacity: int, missing: float) -> None:
        self.missing = missing
        self.lane = np.full(capacity, NOT_ASKED, dtype=np.int64)
        self.again = np.full(capacity, -np.inf)
        self.value = np.full(capacity, missing)
        self.offset = np.zeros(capacity)  # a second value SUMO gave with it (0: none)

    def due(self, slots: np.ndarray, lanes: np.ndarray, step: int) -> np.ndarray:
        """Indices into ``slots`` (vehicles on lane codes ``lanes``) to ask at ``step``."""
        if _lane_due is not None and type(step) is int:  # road/kernels.c: one pass, not seven
            out = np.empty(len(slots), np.int64)
            count = _lane_due(self.lane, self.again, slots, lanes, step, out)
            if count >= 0:
                return out[:count]
        return ((self.lane[slots] != lanes) | (self.again[slots] <= step)).nonzero()[0]

    def store(
        self,
        slots: np.ndarray,
        lanes: np.ndarray,
        values: np.ndarray,
        again: np.ndarray,
        offset: np.ndarray | None = None,
    ) -> None:
        """What SUMO said now: ``values`` (and ``offset``) on lane codes ``lanes``
        (``NOT_ASKED``: ask again next step), due again from step ``again``."""
        self.lane[slots] = lanes
        self.value[slots] = values
        self.again[slots] = again
        if offset is not None:
            self.offset[slots] = offset

    def put(self, slot: int, lane: int, value: float, again: float, offset: float = 0.0) -> None:
        """``store`` of one slot (scalar writes: a few vehicles a step)."""
        self.lane[slot] = lane
        self.value[slot] = value
        self.again[slot] = again
        self.offset[slot] = offset

    def forget(self, slots: np.ndarray) -> None:
        self.lane[slots] = NOT_ASKED
        self.again[slots] = -np.inf

    def grow(self) -> None:
        self.lane = _grown(self.lane, NOT_ASKED)
        self.again = _grown(self.again, -np.inf)
        self.value = _grown(self.value, self.missing)
        self.offset = _grown(self.offset, 0.0)


class VehicleSlots:
    """A slot (row) per vehicle a driver met, and the arrays of what it keeps per slot."""

    def __init__(self, capacity: int = 256) -> None:
        self.of: dict[str, int] = {}
        self.decel = np.full(capacity, np.nan)  # its demand vType's decel [m/s^2] (``take``)
        self.vmax = np.full(capacity, np.inf)  # its demand vType's maxSpeed [m/s] (``take``)
        self.accel = np.full(capacity, np.inf)  # its demand vType's accel [m/s^2] (``take``)
        # Its demand vType's length + minGap [m] (``take``; ``merge_yield.handover_m``).
        self.with_gap = np.full(capacity, np.nan)
        self.last_mps = np.full(capacity, -np.inf)
        # Its driver's desired-speed factor (``policy.driver_speed``; NaN: not drawn yet).
        self.factor = np.full(capacity, np.nan)
        # SUMO's lane changer's look-ahead speed (``merge_yield.handover_m``; NaN: none yet).
        self.lookahead_mps = np.full(capacity, np.nan)
        self.lane_end = LaneCache(capacity, np.nan)  # distance to its lane's end [m]
        self.dark = LaneCache(capacity, np.inf)  # inf: no signal ahead on its route
        # The slots commanded at the last command (``commanded``).
        self.commanded_slots = np.empty(0, dtype=np.int64)

    def add(self, vehicle_id: str) -> None:
        """A slot for a vehicle met for the first time (arrays grown by doubling)."""
        slot = len(self.of)
        self.of[vehicle_id] = slot
        if slot == len(self.last_mps):
            self.decel = _grown(self.decel, np.nan)
            self.vmax = _grown(self.vmax, np.inf)
            self.accel = _grown(self.accel, np.inf)
            self.with_gap = _grown(self.with_gap, np.nan)
            self.last_mps = _grown(self.last_mps, -np.inf)
            self.factor = _grown(self.factor, np.nan)
            self.lookahead_mps = _grown(self.lookahead_mps, np.nan)
            self.lane_end.grow()
            self.dark.grow()

    def slots(self, vehicle_ids: list[str]) -> np.ndarray:
        """The slots of vehicles already met."""
        return codes(self.of, vehicle_ids)  # KeyError for one not met

    def forget(self, vehicle_ids: list[str]) -> None:
        """Vehicles handed back to SUMO: no last command to compare with, caches dropped
        (a driver's factor stays: kept while it is driven, and on re-entry)."""
        s = self.slots(vehicle_ids)
        self.last_mps[s] = -np.inf
        self.lookahead_mps[s] = np.nan
        self.lane_end.forget(s)
        self.dark.forget(s)

    def commanded(self, slots: np.ndarray, cmd: np.ndarray) -> None:
        """The commands of this step: the last command of exactly these slots."""
        self.last_mps[self.commanded_slots] = _NO_COMMAND
        self.last_mps[slots] = cmd
        self.commanded_slots = slots

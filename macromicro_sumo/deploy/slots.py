"""Per-vehicle values a speed-commanding driver keeps across steps (``deploy.drivers``), as
numpy arrays indexed by a stable slot per vehicle: one look-up of the slots per step, then
array indexing, instead of a dictionary look-up per vehicle and value (Bremen's
deployment: ~45 driven vehicles a step, where numpy's fixed cost per call and Python's per
vehicle were most of the driver's time, ``scripts/bench_deploy.py``).

What is kept per slot: the last step's speed command (``last_mps``, -inf: none, or none to
compare with) and the two caches of what SUMO was asked about the vehicle's lane
(``lane_end``: where it must have left its lane; ``dark``: no signal ahead on its route),
each as (lane code, value, step from which it is asked again), "not asked" being lane code
``NOT_ASKED`` and step -inf, so that every check is one comparison of integer arrays.
"""

from __future__ import annotations

import numpy as np

NOT_ASKED = -1  # lane code of a cache entry that was never filled (or was dropped)


class VehicleSlots:
    """A slot (row) per vehicle a driver met, and the arrays of what it keeps per slot."""

    def __init__(self, capacity: int = 256) -> None:
        self.of: dict[str, int] = {}
        self.decel = np.full(capacity, np.nan)  # its demand vType's decel [m/s^2] (``take``)
        self.last_mps = np.full(capacity, -np.inf)
        self.end_lane = np.full(capacity, NOT_ASKED, dtype=np.int64)
        self.end_m = np.full(capacity, np.nan)
        self.end_again = np.full(capacity, -np.inf)
        self.dark_lane = np.full(capacity, NOT_ASKED, dtype=np.int64)
        self.dark_again = np.full(capacity, -np.inf)
        # The slots commanded at the last command (``commanded``).
        self.commanded_slots = np.empty(0, dtype=np.int64)

    def add(self, vehicle_id: str) -> None:
        """A slot for a vehicle met for the first time (arrays grown by doubling)."""
        slot = len(self.of)
        self.of[vehicle_id] = slot
        if slot == len(self.last_mps):
            for name, fill in (
                ("decel", np.nan),
                ("last_mps", -np.inf),
                ("end_lane", NOT_ASKED),
                ("end_m", np.nan),
                ("end_again", -np.inf),
                ("dark_lane", NOT_ASKED),
                ("dark_again", -np.inf),
            ):
                old = getattr(self, name)
                grown = np.full(2 * len(old), fill, dtype=old.dtype)
                grown[: len(old)] = old
                setattr(self, name, grown)

    def slots(self, vehicle_ids: list[str]) -> np.ndarray:
        """The slots of vehicles already met."""
        return np.fromiter(map(self.of.__getitem__, vehicle_ids), np.int64, len(vehicle_ids))

    def forget(self, vehicle_ids: list[str]) -> None:
        """Vehicles handed back to SUMO: no last command to compare with, caches dropped."""
        s = self.slots(vehicle_ids)
        self.last_mps[s] = -np.inf
        self.end_lane[s] = NOT_ASKED
        self.end_again[s] = -np.inf
        self.dark_lane[s] = NOT_ASKED
        self.dark_again[s] = -np.inf

    def commanded(self, slots: np.ndarray, cmd: np.ndarray) -> None:
        """The commands of this step: the last command of exactly these slots."""
        self.last_mps[self.commanded_slots] = -np.inf
        self.last_mps[slots] = cmd
        self.commanded_slots = slots

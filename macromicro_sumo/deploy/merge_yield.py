"""The merges of a speed-commanding driver (``deploy.drivers.SectionSpeedDriver``,
``deploy.merge``): which driven vehicles merge with SUMO's own model (the hand-over, from
``deploy.lane_change``'s reach) and the speed a merge asks of a commanded vehicle that
blocks it (the yield). A mixin: the driver holds the state (``slots``, ``merging``)."""

from __future__ import annotations

from itertools import compress

import numpy as np

from macromicro_sumo.deploy.lane_change import lookahead_speeds, strategic_reach_m
from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.slots import VehicleSlots
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.simulation import Simulation

# Merges (``deploy.merge``). SUMO's lane changer asks for speeds (a merging vehicle adapts
# to its target lane's leader and follower, or stops at its lane's end; a follower there
# slows to open a gap) that a speed command overrides: with every vehicle commanded the
# speed SUMO's car-following would choose (getFollowSpeed), a dense 2-lane merge queued 326
# vehicle-steps at the acceleration lane's end where SUMO alone queued none, and Bremen's
# 419 where SUMO alone queued 73 (docs/deploy.md, "Merges"). "handover": a driven vehicle
# that must leave its lane merges with SUMO's own model from where SUMO's lane changer
# (LC2013) makes that change urgent (``handover_m``, ``deploy.lane_change``); "sumo":
# also, a driven vehicle that blocks its change (SUMO's blocking left follower) takes SUMO's
# own speed where SUMO wanted more than MERGE_YIELD_TOLERANCE_MPS less than both its speed
# and its car-following (Krauss' dawdling is at most sigma accel dt = 0.65 m/s at SUMO's
# defaults).
MERGE_YIELD_TOLERANCE_MPS = 1.0


class MergeYield:
    """``deploy.merge`` for ``SectionSpeedDriver``: the hand-over and the yield."""

    sc: SectionScenario
    slots: VehicleSlots
    stats: DriveStats
    merge: str  # "none", "handover" or "sumo" (with the yield)
    merging: set[str]  # driven vehicles merging with SUMO's own model now
    mode: int  # the commanded vehicles' speed mode

    def handover_m(self, vids: list[str], slots: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """Per driven vehicle ``strategic_reach_m`` (0: no change needed), after updating
        each one's look-ahead speed."""
        la = self.slots.lookahead_mps[slots]
        la = lookahead_speeds(la, speed, self.sc.simulation.step_length_s)
        self.slots.lookahead_mps[slots] = la
        offset = self.slots.lane_end.offset[slots]
        if not np.count_nonzero(offset):  # nobody must change lane: 0 for all, as below
            return np.zeros(len(vids))
        return strategic_reach_m(offset, la, self.slots.with_gap[slots])

    def merges(self, sim: Simulation, vids: list[str], ahead_m: np.ndarray,
               reach_m: np.ndarray) -> np.ndarray | None:  # fmt: skip
        """``deploy.merge`` "handover" or "sumo", from ``ahead_m``, each driven vehicle's
        distance to where it must have left its lane: which of ``vids`` are commanded this
        step (those that must leave their lane within ``reach_m``, ``handover_m``, merge
        with SUMO's own model, handed over until they are on a lane that carries them on;
        None: all). ``merging`` holds the others."""
        must_now = ahead_m <= reach_m
        if not self.merging and not np.count_nonzero(must_now):
            return None  # nobody merging, before or now
        now = set(compress(vids, must_now.tolist()))
        if now - self.merging:
            sim.release_speeds(sorted(now - self.merging))
        back = sorted(self.merging - now)
        if back:
            sim.set_speed_mode(back, self.mode)
        self.merging = now
        self.stats.vehicle_steps_driven -= len(now)
        return ~must_now if now else None

    def blocking(self, sim: Simulation, vids: list[str]) -> list[int]:
        """``deploy.merge`` "sumo": the indices among the commanded ``vids`` of those that
        block a merging vehicle's change (SUMO's blocking left follower, whom its lane
        changer asks to cooperate), the candidates for SUMO's cooperative slow-down
        (``yields``). Only a blocking follower: every vehicle on the target lane taking
        SUMO's lower speed slowed Bremen's stream by 2 m/s (run 1)."""
        if self.merge != "sumo" or not self.merging:
            return []
        blockers = sim.left_blockers(sorted(self.merging))
        return [i for i, v in enumerate(vids) if v in blockers]

    def yields(
        self, sim: Simulation, vids: list[str], near: list[int], speed: np.ndarray, safe: np.ndarray
    ) -> np.ndarray:
        """Per commanded vehicle ``vids`` (speeds ``speed``, safe speeds behind what each
        sees ahead ``safe``: the safety layer's), the speed a merge asks of it: SUMO's own
        speed where it blocks a merging vehicle (indices ``near``) and SUMO wanted it more
        than ``MERGE_YIELD_TOLERANCE_MPS`` slower than both its speed and its car-following
        (the safe speed: where SUMO's own speed is below it too, its lane changer asked for
        less, a cooperative slow-down; SUMO's car-following is not imposed on the policy);
        inf: none."""
        cap = np.full(len(vids), np.inf)
        own = sim.own_speeds([vids[i] for i in near])
        asked = own < np.minimum(speed[near], safe[near]) - MERGE_YIELD_TOLERANCE_MPS
        cap[near] = np.where(asked, own, np.inf)
        return cap

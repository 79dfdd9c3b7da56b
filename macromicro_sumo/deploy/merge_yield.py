"""The merges of a speed-commanding driver (``deploy.drivers.SectionSpeedDriver``,
``deploy.merge``): which driven vehicles merge with SUMO's own model (the hand-over, from
``deploy.lane_change``'s reach) and the speed a merge asks of a commanded vehicle that
blocks it (the yield). A mixin: the driver holds the state (``slots``, ``merging``)."""

from __future__ import annotations

from itertools import compress
from operator import gt
from typing import Protocol

import numpy as np

from macromicro_sumo.deploy.lane_change import (
    continuation_lanes,
    lookahead_speeds,
    strategic_reach_m,
    usable_distance_m,
)
from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.slots import VehicleSlots
from macromicro_sumo.road.physics import count_nonzero
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates

# Merges (``deploy.merge``). SUMO's lane changer asks for speeds (a merging vehicle adapts
# to its target lane's leader and follower, or stops at its lane's end; a follower there
# slows to open a gap) that a speed command overrides: with every vehicle commanded the
# speed SUMO's car-following would choose (getFollowSpeed), a dense 2-lane merge queued 326
# vehicle-steps at the acceleration lane's end where SUMO alone queued none, and Bremen's
# 419 where SUMO alone queued 73 (docs/deploy-log.md, "Merges"). "handover": a driven vehicle
# that must leave its lane merges with SUMO's own model from where SUMO's lane changer
# (LC2013) makes that change urgent (``handover_m``, ``deploy.lane_change``); "sumo":
# also, a driven vehicle that blocks its change (SUMO's blocking left follower) takes SUMO's
# own speed where SUMO wanted more than MERGE_YIELD_TOLERANCE_MPS less than both its speed
# and its car-following (Krauss' dawdling is at most sigma accel dt = 0.65 m/s at SUMO's
# defaults).
MERGE_YIELD_TOLERANCE_MPS = 1.0
# A lane that carries a vehicle on is asked again (SUMO's best lanes, one call per vehicle)
# this many steps later: SUMO sees a lane's end only within its look-ahead (~3 km), which
# a vehicle nears by at most a few hundred metres meanwhile; a lane end, once seen, stays.
LANE_END_RECHECK_STEPS = 20
# ``deploy.merge_follow = "last_lane"``: only a blocker at this speed or more follows
# (``last_lanes``). A slower one follows LC2013's stop-and-go asks in a queue: drawn 501's
# 4-2-1 chain (its blockers' median 5.1 m/s, 1803's 20.7). All 4 runs, policy, from
# every speed / 15 / 20 / 25 m/s: 1803 2.558 / 2.212 / 2.026 / 2.408 (3.259 off), 501
# 2.543 / 2.405 / 2.230 / 1.986 (1.989), 1045 1.724 / 1.744 / 1.622 / 1.661 md5-equal
# (1.661), 522 2.619 / 2.491 / 2.255 / 2.318 md5-equal (2.318; hD50, stop 50).
FOLLOW_MIN_MPS = 25.0
# ``deploy.merge_follow = "last_lane"``: a blocker that may follow (``last_lanes``, at
# ``FOLLOW_MIN_MPS`` or more) on a lane moving at ``FOLLOW_FREE_FRACTION`` of its limit or
# more (``free_lanes``) yields where SUMO's own speed is ``deploy.merge_follow_tolerance_mps``
# (0.5) below its speed and safe speed, not ``MERGE_YIELD_TOLERANCE_MPS``. LC2013 asks the follower of an
# urgent merger far behind it to fall back gently, 0.1-0.9 m/s a 0.5 s step (1803, run 2:
# for 10 s, closing 70 -> 30 m at 29 -> 27 m/s); never asked at 1 m/s, it stayed beside the
# merger, which stood 100 s at the lane end. All 4 runs, policy (hD51, stop 51): 1803
# 2.398 -> 1.410 m/s (standing at the drop 22 -> 9 vehicles; the truth 1), 501 2.416 ->
# 2.260; without the lane gate 501 lost (2.672): its last lanes queue, at capacity.
FOLLOW_FREE_FRACTION = 0.6


def yield_caps(
    own: np.ndarray,
    speed: np.ndarray,
    safe: np.ndarray,
    decel: np.ndarray,
    dt_s: float,
    held: np.ndarray | None = None,
    follow: np.ndarray | None = None,
    gentle: np.ndarray | None = None,
    gentle_tolerance_mps: float = MERGE_YIELD_TOLERANCE_MPS,
) -> tuple[np.ndarray, np.ndarray]:
    """The merge yield's caps [m/s] (``MergeYield.yields``) of blocking vehicles at speeds
    ``speed``, safe speeds ``safe``, vType decels ``decel``, from SUMO's own speeds ``own``
    (the last step's, getSpeedWithoutTraCI), and where SUMO asked for them: ``own`` where
    it is more than ``MERGE_YIELD_TOLERANCE_MPS`` below both the speed and the safe speed
    (its lane changer asked for less), at least v - decel dt (``own`` was chosen from last
    step's speed); inf where not asked. ``held`` (``deploy.merge_reach = "occupation"``):
    the vehicles SUMO asked last step; one not asked now is held at its speed for this
    step, no acceleration. Why: the step after a yield SUMO's own speed is the one it chose
    from the speed before the yield, about the yield's cap, so it is not asked again; the
    policy then accelerated the blocker by up to 2.6 m/s^2 and the next step's own speed
    braked it again, on/off every other step (occupation, all 4 runs: of the yields whose
    vehicle still blocked the next step, 4,906 of 5,518 free then on drawn 549, 884 of 919
    on Bremen; held, none). Held while it blocks (a hold after a hold) held blockers up to
    33 s and 549's run 2 went 3.63 -> 6.10 m/s (docs/deploy-log.md, stop 42, hO).
    ``follow`` (with ``held``; ``deploy.merge_follow``): where on, a held vehicle SUMO wants
    slower by any amount takes ``own`` (at least v - decel dt) and counts as asked, so it
    stays held while SUMO wants it slower. ``gentle``: where on, a vehicle is asked where
    ``own`` is more than ``gentle_tolerance_mps`` below (``deploy.merge_follow_tolerance_mps``,
    ``MergeYield.blocking``)."""
    low = np.minimum(speed, safe)
    asked = own < low - MERGE_YIELD_TOLERANCE_MPS
    if gentle is not None:  # a free-flowing follower yields to a gentler ask
        asked |= gentle & (own < low - gentle_tolerance_mps)
    cap = np.where(asked, np.maximum(own, speed - decel * dt_s), np.inf)
    if held is not None:
        cap = np.where(held & ~asked, speed, cap)
        if follow is not None:
            # ``deploy.merge_follow``: a held blocker that may follow takes SUMO's own slower
            # speed by any amount and stays held while it does (``last_lanes``).
            keep = held & ~asked & follow & (own < speed)
            cap = np.where(keep, np.maximum(own, speed - decel * dt_s), cap)
            asked = asked | keep
    return cap, asked


def last_lanes(section: Section) -> frozenset[str]:
    """The leftmost lane of each of ``section``'s edges (no internal lane): the blockers
    ``deploy.merge_follow = "last_lane"`` keeps on SUMO's speed (``yield_caps``' follow)
    where they run at ``FOLLOW_MIN_MPS`` or more.
    Why: a blocker there has no lane to move over to, only its speed opens its merger's gap;
    LC2013 asks it to fall back by less than ``MERGE_YIELD_TOLERANCE_MPS`` a step, so a
    yield, a hold and a release kept it level with the merger (fresh motorway 1803, 4 -> 1:
    the merger stood at the lane end, hF49). On a lane with one to its left (Bremen's
    on-ramp, 549's 3 -> 2) the follower moves over instead, and following SUMO there too
    cost Bremen 0.914 -> 1.374 m/s (hF49's follow-hold experiment)."""
    lanes = zip(section.edge_ids, section.n_lanes.tolist(), strict=True)
    return frozenset(f"{edge}_{n - 1}" for edge, n in lanes)


def free_lanes(
    section: Section, lanes: set[str], on: list[str], speed: np.ndarray
) -> frozenset[str]:
    """Those of ``lanes`` (the section's, not internal) whose vehicles now (on lanes ``on``
    at speeds ``speed``, every vehicle's) move at ``FOLLOW_FREE_FRACTION`` of the lane's
    speed limit or more on average: the lanes where a follower yields to LC2013's gentle
    ask (``yield_caps``' gentle). Why: on a lane at capacity, its vehicles queueing (drawn
    501's 4 -> 2 -> 1 at 1.25 x capacity), the gentle yield lost 2.416 -> 2.672 m/s (all
    4 runs, policy); in free flow (1803's through lane at 22-27 m/s of 34.4) it gained."""
    free = set()
    for lane in lanes:
        e, i = section.lanes[lane][:2]
        mean = float(np.mean(speed[[x == lane for x in on]]))
        if mean >= FOLLOW_FREE_FRACTION * float(section.limits_mps[e, i]):
            free.add(lane)
    return frozenset(free)


def drop_chain_lanes(section: Section) -> frozenset[str]:
    """The lanes of ``section`` on which ``deploy.merge_reach = "occupation"`` acts: those
    whose chain along the section's route ends (``Section.end_beyond_m[1]`` finite: a lane
    drop, an acceleration lane, an exit-only lane; ``deploy.lane_change``) and the
    junctions' internal lanes. Why: occupation's reach (the hand-over at LC2013's usable
    distance, the yield to every vehicle that must change) is for the lanes that end; a
    turner's change onto its turning lane is not a lane drop, and occupation on it cost
    arterial 837 0.896 -> 0.913 m/s (all 4 runs, policy; with it restricted, md5-equal to
    plain, stop 46, hM46/hN46)."""
    chain = section.end_beyond_m[1]
    return frozenset(
        lane
        for lane, (e, i, _start, _per_m) in section.lanes.items()
        if lane.startswith(":") or bool(np.isfinite(chain[e, i]))
    )


class LaneEnds(Protocol):
    """What ``MergeYield.must_change`` and ``MergeYield.yields`` ask of the class they are
    mixed into (``SectionSpeedDriver``): its state (the scenario, for the step length; each
    vehicle's vType decel, ``SectionDriver.decel_of``), the slots and lane codes of
    vehicles (``slots_of``) and the one lane-end cache (``lane_end_m``)."""

    sc: SectionScenario
    decel_of: dict[str, float]
    yield_all: bool
    drop_lanes: frozenset[str]
    yielded: frozenset[str]
    slots: VehicleSlots
    section: Section
    driven: set[str]
    others: set[str]
    steps: int
    flags: tuple[VehicleStates | None, list[bool], list[bool]]  # ``SectionDriver.before_step``
    _plain: frozenset[str] | None
    _last_others: tuple[list[str], list[str], float, list[str]] | None

    def slots_of(self, vids: list[str], lanes: list[str]) -> tuple[np.ndarray, np.ndarray]: ...

    def lane_end_m(self, sim: Simulation, vids: list[str], lanes: list[str],
                   at: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray: ...  # fmt: skip


class MergeYield:
    """``deploy.merge`` for ``SectionSpeedDriver``: the hand-over and the yield.

    ``occupation`` and ``yield_all`` (``deploy.merge_reach = "occupation"`` sets both, the
    default since stop 46, with merge "sumo"): the hand-over at LC2013's usable distance, the distance left less the best
    lane's occupation (``occupations_m``), and the yield to the blockers of every vehicle
    that must leave its lane (``must_change``). On drawn 522 (2 lanes dropping to 1 in a queue) the
    truth's cars leave the ending lane all along it, the commanded ones stayed on to
    400-600 m and zippered in at its end, the through lane jammed (8 against 13 m/s). Both
    on, all 4 runs, speed RMSE: 522 3.39 -> 3.42 m/s ("memory"; m0's 375 m station -3.27
    -> +0.95 m/s bias, downstream slower through memory's entry factors), 2.86 with
    "drawn"; 549 4.53 -> 3.82; 501 3.02 -> 2.72 (held-out 3.23 -> 4.00); Bremen 1.15 ->
    1.19; netgen_corridor and arterial 521 the same. The occupation alone costs 549
    (5.55), the yield alone 549 and 501 (4.72, 3.09). A vehicle SUMO asked to yield is
    held at its speed the next step (``yield_caps``)."""

    sc: SectionScenario
    slots: VehicleSlots
    stats: DriveStats
    merge: str  # "none", "handover" or "sumo" (with the yield)
    merging: set[str]  # driven vehicles merging with SUMO's own model now
    mode: int  # the commanded vehicles' speed mode
    section: Section
    shape_of: dict[str, tuple[float, float, float]]
    decel_of: dict[str, float]  # vehicle -> its demand vType's decel (``SectionDriver``)
    occupation = False  # the hand-over at LC2013's usable distance (``usable_m``)
    yield_all = False  # the yield to the blockers of every vehicle that must change
    # With ``occupation``: the lanes it acts on (``drop_chain_lanes``), set with it
    drop_lanes: frozenset[str] = frozenset()
    # With ``yield_all``: the vehicles SUMO asked to yield last step (``yield_caps``' held)
    yielded: frozenset[str] = frozenset()
    # With ``deploy.merge_follow = "last_lane"``: this step's blockers that follow SUMO's
    # own speed while held (on a ``last_lanes`` lane), and those lanes, once
    follows: frozenset[str] = frozenset()
    gentle: frozenset[str] = frozenset()  # of ``follows``, those on a ``free_lanes`` lane
    _last_lanes: frozenset[str] | None = None
    _chains: dict[str, tuple[str, ...]] | None = None
    _plain: frozenset[str] | None = None  # the section's lanes that are not internal ones
    # ``must_change``'s last vehicles not driven: (ids, lanes, step due again, must change)
    _last_others: tuple[list[str], list[str], float, list[str]] | None = None
    driven: set[str]
    steps: int
    # vehicles not driven on the section with an entry in ``slots.lane_end`` (``must_change``)
    others: set[str]

    def occupations_m(
        self, rows: np.ndarray, lanes: list[str], slots: np.ndarray, st: VehicleStates
    ) -> np.ndarray:
        """Per driven vehicle (rows ``rows`` of ``st``, on ``lanes``), the occupation of
        its best lane as LC2013 reads it (``deploy.lane_change.JAM_FACTOR``): the length +
        minGap of the vehicles ahead of it on the lane ``offset`` lanes over on its edge,
        plus those on every lane of that lane's continuation in the section
        (``continuation_lanes``); 0 where it needs no change (or is on a junction)."""
        offset = self.slots.lane_end.offset[slots]
        occ = np.zeros(len(rows))
        best: dict[int, str] = {}
        for i in offset.nonzero()[0].tolist():  # offset is 1-D: flatnonzero's call less
            lane = lanes[i]
            if not lane.startswith(":"):
                edge, _, k = lane.rpartition("_")
                target = f"{edge}_{int(k) + int(offset[i])}"
                if target in self.section.lanes:
                    best[i] = target
        if not best:
            return occ
        if self._chains is None:
            self._chains = continuation_lanes(self.section)
        chains = self._chains
        on: dict[str, list[int]] = {}
        for lane in best.values():
            on[lane] = []
            for c in chains.get(lane, ()):
                on[c] = []
        # The rows on those lanes, in order: filtered in C, not a Python step per vehicle.
        all_lanes = st.lanes
        for j in compress(range(len(all_lanes)), map(on.__contains__, all_lanes)):
            on[all_lanes[j]].append(j)
        ids, pos, shape = st.ids, st.pos_m, self.shape_of
        brutto = {
            lane: np.array([shape[ids[j]][0] + shape[ids[j]][1] for j in js])
            for lane, js in on.items()
        }
        # Summed where a continuation reads it (a best lane alone needs none); the positions
        # on a best lane taken once for all its vehicles.
        targets = set(best.values())
        total = {c: float(brutto[c].sum()) for t in targets for c in chains.get(t, ())}
        at = {t: pos[on[t]] for t in targets if on[t]}
        for i, lane in best.items():
            ahead = float(brutto[lane][at[lane] > pos[rows[i]]].sum()) if lane in at else 0.0
            occ[i] = ahead + sum(total[c] for c in chains.get(lane, ()))
        return occ

    def usable_m(
        self,
        ahead_m: np.ndarray,
        rows: np.ndarray,
        lanes: list[str],
        slots: np.ndarray,
        st: VehicleStates,
    ) -> np.ndarray:
        """``ahead_m`` (to where each driven vehicle must have left its lane) as the
        hand-over reads it: LC2013's usable distance with ``occupation``, else as it is."""
        if not self.occupation:
            return ahead_m
        usable = usable_distance_m(ahead_m, self.occupations_m(rows, lanes, slots, st))
        # Only on the lanes that end (``drop_chain_lanes``): a turner keeps the plain reach.
        drop = np.fromiter(map(self.drop_lanes.__contains__, lanes), bool, len(lanes))
        return np.where(drop, usable, ahead_m)

    def handover_m(
        self, vids: list[str], slots: np.ndarray, speed: np.ndarray
    ) -> np.ndarray | None:
        """Per driven vehicle ``strategic_reach_m`` (0: no change needed), after updating
        each one's look-ahead speed; None where none needs a change (0 for all)."""
        la = self.slots.lookahead_mps[slots]
        la = lookahead_speeds(la, speed, self.sc.simulation.step_length_s)
        self.slots.lookahead_mps[slots] = la
        offset = self.slots.lane_end.offset[slots]
        if not count_nonzero(offset):  # nobody must change lane: 0 for all
            return None
        return strategic_reach_m(offset, la, self.slots.with_gap[slots])

    def handed_over(
        self,
        sim: Simulation,
        vids: list[str],
        ahead_m: np.ndarray,
        rows: np.ndarray,
        lanes: list[str],
        slots: np.ndarray,
        speed: np.ndarray,
        st: VehicleStates,
    ) -> np.ndarray | None:
        """``merges`` from ``handover_m``'s reach and ``usable_m``'s distance left (``ahead_m``:
        to each one's lane end) of the driven ``vids`` (rows ``rows`` of ``st``, speeds
        ``speed``): which are commanded this step (None: all). Where nobody must change lane
        (a finite lane end comes with its offset: every end inf, none within a reach of 0)
        and nobody is merging, all, without the occupations' and the reach's array calls
        (the same answer: ``merges`` keeps all then)."""
        reach = self.handover_m(vids, slots, speed)
        if reach is None and not self.merging:
            return None
        usable = self.usable_m(ahead_m, rows, lanes, slots, st)
        return self.merges(sim, vids, usable, np.zeros(len(vids)) if reach is None else reach)

    def merges(self, sim: Simulation, vids: list[str], ahead_m: np.ndarray,
               reach_m: np.ndarray) -> np.ndarray | None:  # fmt: skip
        """``deploy.merge`` "handover" or "sumo", from ``ahead_m``, each driven vehicle's
        distance to where it must have left its lane: which of ``vids`` are commanded this
        step (those that must leave their lane within ``reach_m``, ``handover_m``, merge
        with SUMO's own model, handed over until they are on a lane that carries them on;
        None: all). ``merging`` holds the others."""
        must_now = ahead_m <= reach_m
        if not self.merging and not count_nonzero(must_now):
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

    def blocking(
        self, sim: Simulation, vids: list[str], slots: np.ndarray, st: VehicleStates
    ) -> list[int]:
        """``deploy.merge`` "sumo": the indices among the commanded ``vids`` (slots
        ``slots``) of those that block a merging vehicle's change (SUMO's blocking left
        follower, whom its lane changer asks to cooperate), the candidates for SUMO's
        cooperative slow-down (``yields``). Only a blocking follower: every vehicle on the
        target lane taking SUMO's lower speed slowed Bremen's stream by 2 m/s (run 1). With
        ``yield_all`` the blockers of every vehicle on the section that must leave its lane
        (``must_change``), not only of the handed-over ones: a commanded one and one SUMO
        drives (an instrumented one) ask for the gap as LC2013 urgently wants it."""
        if self.merge != "sumo":
            return []
        asking = set(self.merging)
        if self.yield_all:
            # Only the changers on the lanes that end (``drop_chain_lanes``), not turners.
            index, on, drop = st.index, st.lanes, self.drop_lanes
            asking.update(
                v
                for v in self.must_change(sim, vids, slots, st)
                if v in index and on[index[v]] in drop
            )
        if not asking:
            self.yielded = frozenset()  # nobody blocks now: none held next step
            return []
        blockers = sim.left_blockers(sorted(asking))
        if self.yield_all and self.sc.deploy.merge_follow == "last_lane":
            if self._last_lanes is None:
                self._last_lanes = last_lanes(self.section)
            index, on, last, v = st.index, st.lanes, self._last_lanes, st.speed_mps
            self.follows = frozenset(
                b
                for b in blockers
                if b in index and on[index[b]] in last and v[index[b]] >= FOLLOW_MIN_MPS
            )
            free = free_lanes(self.section, {on[index[b]] for b in self.follows}, on, v)
            self.gentle = frozenset(b for b in self.follows if on[index[b]] in free)
        near = list(compress(range(len(vids)), map(blockers.__contains__, vids)))  # in C
        if not near:
            self.yielded = frozenset()
        return near

    def must_change(
        self: LaneEnds, sim: Simulation, vids: list[str], slots: np.ndarray, st: VehicleStates
    ) -> list[str]:
        """The vehicles on the section's lanes that must leave their lane to the left for
        their route (SUMO's best-lane offset > 0, where ``left_blockers`` are the followers
        that block it): the commanded ``vids`` (slots ``slots``) and the vehicles not
        driven, all from the one lane-end cache (``lane_end_m``: asked once per vehicle and
        lane, a lane that carries one on again ``LANE_END_RECHECK_STEPS`` later). A vehicle
        not driven that left the section's lanes since the last call is dropped from it
        (``others``), as ``release`` drops a driven one."""
        cache = self.slots.lane_end
        out = list(compress(vids, (cache.offset[slots] > 0).tolist()))
        # Not driven, on the section: on its lanes and not in the population (the driven
        # ones are the population's there, ``before_step``, whose flags these are), filtered
        # in C; without this step's flags, from ``driven``.
        held, on, ours = self.flags
        if held is not st:
            on = list(map(self.section.lanes.__contains__, st.lanes))
            ours = list(map(self.driven.__contains__, st.ids))
        keep = list(map(gt, on, ours))  # on and not ours (bools: True > False alone)
        ids, lanes = list(compress(st.ids, keep)), list(compress(st.lanes, keep))
        gone = self.others.difference(ids)
        if gone:
            cache.forget(self.slots.slots(sorted(gone)))
            self.others.difference_update(gone)
            self._last_others = None  # a forgotten entry is asked again if it comes back
        # Not on a junction's internal lane: SUMO's best lanes there are the next edge's.
        if self._plain is None:
            self._plain = frozenset(k for k in self.section.lanes if not k.startswith(":"))
        plain = list(map(self._plain.__contains__, lanes))
        if not all(plain):
            ids, lanes = list(compress(ids, plain)), list(compress(lanes, plain))
        if not ids:
            return out
        # The same vehicles on the same lanes as at the last call, none due again yet: their
        # entries are as they were (only this method writes those slots; the lanes equal,
        # each entry's lane is its lane's), so are their offsets.
        last = self._last_others
        if last is not None and self.steps < last[2] and last[0] == ids and last[1] == lanes:
            out.extend(last[3])
            return out
        at = self.slots_of(ids, lanes)
        self.lane_end_m(sim, ids, lanes, at)
        self.others.update(ids)
        # The arrays as they are now: a new slot may have grown them.
        cache = self.slots.lane_end
        change = list(compress(ids, (cache.offset[at[0]] > 0).tolist()))
        self._last_others = (ids, lanes, float(cache.again[at[0]].min()), change)
        out.extend(change)
        return out

    def yields(
        self: LaneEnds,
        sim: Simulation,
        vids: list[str],
        near: list[int],
        speed: np.ndarray,
        safe: np.ndarray,
    ) -> np.ndarray:
        """Per commanded vehicle ``vids`` (speeds ``speed``, safe speeds behind what each
        sees ahead ``safe``: the safety layer's), the speed a merge asks of it: SUMO's own
        speed where it blocks a merging vehicle (indices ``near``) and SUMO wanted it more
        than ``MERGE_YIELD_TOLERANCE_MPS`` slower than both its speed and its car-following
        (the safe speed: where SUMO's own speed is below it too, its lane changer asked for
        less, a cooperative slow-down; SUMO's car-following is not imposed on the policy);
        inf: none. At least v - decel dt, the vehicle's vType's decel: SUMO's own speed is
        the last step's, chosen from the speed it had then; where the command accelerated
        it since, that speed asked now brakes harder than its decel, which a follower SUMO
        drives does not plan for (drawn 501: 3.36 -> 0 m/s in a step, 6.7 m/s^2, and the
        car just merged behind it collided). With ``yield_all`` a vehicle SUMO asked last
        step and not now is held at its speed for this step (``yield_caps``)."""
        cap = np.full(len(vids), np.inf)
        ids = [vids[i] for i in near]
        decel = np.fromiter(map(self.decel_of.__getitem__, ids), float, len(ids))
        held = follow = gentle = None
        if self.yield_all:
            held = np.fromiter(map(self.yielded.__contains__, ids), bool, len(ids))
            if self.sc.deploy.merge_follow == "last_lane":
                follow = np.fromiter(map(self.follows.__contains__, ids), bool, len(ids))
                gentle = np.fromiter(map(self.gentle.__contains__, ids), bool, len(ids))
        got, asked = yield_caps(
            sim.own_speeds(ids),
            speed[near],
            safe[near],
            decel,
            self.sc.simulation.step_length_s,
            held,
            follow,
            gentle,
            self.sc.deploy.merge_follow_tolerance_mps,
        )
        if self.yield_all:
            self.yielded = frozenset(compress(ids, asked.tolist()))
        cap[near] = got
        return cap

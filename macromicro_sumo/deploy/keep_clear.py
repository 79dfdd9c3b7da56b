"""``deploy.keep_clear``: a driven vehicle does not drive into a signalised junction it cannot
leave, as SUMO's drivers (``MSVehicle::checkRewindLinkLanes`` with
``getSpaceTillLastStanding``): from the lane past the junction, the room up to the back of its
upstream-most waiting vehicle (slower than ``WAITING_MPS``), less every moving vehicle's
length and minGap behind that one, less the vehicles' ahead of the driver on its own lane and
in the junction, must hold the driver's length and minGap; else it stops at its line though
the light is green. A lane past the junction with no waiting vehicle leaves room further on
(SUMO adds the next lanes' space): no stop.

Why: under speed commands (``deploy.safety.SPEED_MODES``: no safe-speed bit) SUMO does not
hold a commanded vehicle at the line for this, and the safety layer followed the leader
past the line into the junction: on arterial 1164 (one lane, 4 signals 274 m apart) the
policy's cars stood or crept inside the first junction 4x as often as the truth's (1,127
against 271 samples below 3 m/s), each green let 1.3 more cars over the first stop line
(14.50 against 13.22) and 6% more cars entered the network (812 against 765 veh/h at the
entry loop) (docs/deploy.md, stop 47, hA47). hA47's rule looked only at the vehicle ahead
past the junction (``"signals"`` in its patch; lost on 1161); this one counts the lane, as
SUMO does. ``KeepClear``: the state one driver owns (its holds, each vehicle's length and
length + minGap as first met); the driver hands the states in.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from itertools import compress, filterfalse

import numpy as np

from macromicro_sumo.road.leaders import STOPLINE_GAP_M
from macromicro_sumo.road.physics import brake_gap
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.net_xml import net_links, once_per_file
from macromicro_sumo.sumo.states import VehicleStates

# SUMO's SUMO_const_haltingSpeed [m/s]: below it a vehicle counts as standing in
# getSpaceTillLastStanding. "lane1" takes 1 m/s instead: the policy's queues creep (hA47:
# the vehicle past 1164's first junction was never below 0.1 m/s while SUMO's stood).
WAITING_MPS = {"lane": 0.1, "lane1": 1.0}
# Length and minGap [m] of a vehicle whose shape the driver has not seen (SUMO's passenger).
DEFAULT_SHAPE = (5.0, 2.5)
DEFAULT_BRUTTO_M = DEFAULT_SHAPE[0] + DEFAULT_SHAPE[1]
_UNSEEN = object()  # a lane ``KeepClear.lane_end_m`` has not met yet


def lane_rooms(
    lanes: Sequence[str],
    pos_m: np.ndarray,
    speed_mps: np.ndarray,
    brutto_m: np.ndarray,
    length_m: np.ndarray,
    waiting_mps: float,
) -> dict[str, float]:
    """Room [m] on each lane holding a waiting vehicle (slower than ``waiting_mps``): the back
    of the upstream-most waiting one (``pos_m`` less ``length_m``) less ``brutto_m`` (length
    plus minGap) of each vehicle behind it; lanes without one are absent (room further on)."""
    on: dict[str, list[int]] = defaultdict(list)
    for r, lane in enumerate(lanes):
        on[lane].append(r)
    out = {}
    for lane, rows in on.items():
        behind = 0.0
        for r in sorted(rows, key=pos_m.__getitem__):  # upstream first, as SUMO's lane
            if speed_mps[r] < waiting_mps:
                out[lane] = float(pos_m[r] - length_m[r]) - behind
                break
            behind += float(brutto_m[r])
    return out


@once_per_file
def signal_ends(net_file: str) -> frozenset[str]:
    """The lanes of ``net_file``'s edges with a signalised link at their end: where the
    junction to keep clear is signalised (hA47's finding; SUMO keeps every junction clear)."""
    net = net_links(net_file)
    return frozenset(ln for c in net.connections if c.tl for ln in net.lanes.get(c.src, ()))


class KeepClear:
    """``deploy.keep_clear`` for one driver (``mode`` "lane" or "lane1", on ``section``,
    steps of ``dt`` [s]): the cars it holds at their line, kept from step to step (held on
    whatever their speed: the brake check is for a new hold only; a car braking for the line
    would fail it near the line and drive in), and each vehicle's length and length + minGap
    [m], kept from the first step it is met with a known shape (before: rebuilt for every
    vehicle on the road every step, a Python loop)."""

    def __init__(self, mode: str, section: Section, dt: float) -> None:
        if mode not in WAITING_MPS:
            raise ValueError(f"deploy.keep_clear: {mode!r} is not one of {sorted(WAITING_MPS)}")
        self.mode, self.section, self.dt = mode, section, dt
        self.waiting_mps = WAITING_MPS[mode]
        self.held: set[str] = set()
        self.length_m: dict[str, float] = {}
        self.brutto_m: dict[str, float] = {}  # length + minGap
        self.lane_end_m: dict[str, float | None] = {}  # ``signal_end`` per lane met

    def meet(self, ids: Sequence[str], shape_of: dict[str, tuple[float, float, float]]) -> None:
        """Keeps the length and length + minGap of each of ``ids`` not met yet whose shape
        (length, minGap, decel) ``shape_of`` holds; one it lacks is asked again next time."""
        for v in filterfalse(self.length_m.__contains__, ids):
            got = shape_of.get(v)
            if got is not None:
                self.length_m[v] = got[0]
                self.brutto_m[v] = got[0] + got[1]

    def signal_end(self, net_file: str, lane: str) -> float | None:
        """The arc length [m] of ``lane`` of the section where a signalised link ends it
        (``signal_ends`` of ``net_file``), as the driver's position counts it; None: no
        signal at its end, or not a section lane."""
        if lane not in signal_ends(net_file) or lane not in self.section.lanes:
            return None
        got = self.section.lanes[lane]
        return float(self.section.lengths_m[got[0]]) / got[3]

    def rooms(self, st: VehicleStates, past: set[str]) -> dict[str, float]:
        """``lane_rooms`` of lanes ``past`` alone (the lanes past a junction some driven car
        asks about): the vehicles on other lanes play no part in these lanes' rooms."""
        rows = list(compress(range(len(st.ids)), map(past.__contains__, st.lanes)))
        if not rows:
            return {}
        ids = [st.ids[r] for r in rows]
        length = np.array([self.length_m.get(v, DEFAULT_SHAPE[0]) for v in ids])
        brutto = np.array([self.brutto_m.get(v, DEFAULT_BRUTTO_M) for v in ids])
        lanes = [st.lanes[r] for r in rows]
        idx = np.array(rows, np.int64)
        return lane_rooms(lanes, st.pos_m[idx], st.speed_mps[idx], brutto, length, self.waiting_mps)

    def lines(
        self,
        net_file: str,
        red: np.ndarray,
        lanes: Sequence[str],
        rows: np.ndarray,
        st: VehicleStates,
        leaders: Sequence[tuple[str, float]],
        vids: Sequence[str],
        shape_of: dict[str, tuple[float, float, float]],
    ) -> np.ndarray:
        """``red`` [m] (each driven vehicle's distance to its next red or yellow line, inf:
        none, NaN: no signal ahead) with a line at its lane's end where it must not enter
        the junction there (``net_file``: the simulation's net). ``st``: every vehicle's
        state, ``rows``: the driven ones' rows, ``lanes`` their lanes; ``leaders``: SUMO's
        (ID, gap) of each; ``shape_of``: vehicle -> (length, minGap, decel) as the driver
        met it. The lane past the junction is the first lane other than the driver's along
        the chain of leaders, past any in the junction (":..."). Returns a new array where
        any line is added, else ``red`` itself."""
        self.meet(st.ids, shape_of)
        index, brutto = st.index, self.brutto_m
        ahead_of: dict[str, str] | None = None  # built at the first car that may wait
        # Plain floats: a numpy scalar's compare or conversion per car cost more (same values).
        red_l, pos_l = red.tolist(), st.pos_m[rows].tolist()
        # Per driven car that may have to wait: (its index, the lane past, the length and
        # minGap of those ahead of it up to that lane, the distance to its lane's end).
        asks: list[tuple[int, str, float, float]] = []
        for i, v in enumerate(vids):
            lane = lanes[i]
            if red_l[i] != red_l[i]:
                continue  # no signal ahead
            at_end = self.lane_end_m.get(lane, _UNSEEN)
            if at_end is _UNSEEN:
                at_end = self.lane_end_m[lane] = self.signal_end(net_file, lane)
            if at_end is None:
                continue  # no signal at its lane's end, or off the section
            end = at_end - pos_l[i]
            if red_l[i] <= end or end <= 0.0:
                continue  # a red or yellow line nearer already (SUMO stops there anyway)
            if ahead_of is None:
                ahead_of = {u: lid for u, (lid, _) in zip(vids, leaders, strict=True) if lid}
            # Vehicles ahead of it on its lane and in the junction must fit too (SUMO's
            # lengthsInFront and the internal lane's vehicles).
            front, lid, past, hops = 0.0, ahead_of.get(v, ""), "", 0
            while lid and hops < 64:
                lr = index.get(lid)
                if lr is None:
                    break
                ll = st.lanes[lr]
                if ll != lane and not ll.startswith(":"):
                    past = ll
                    break
                front += brutto.get(lid, DEFAULT_BRUTTO_M)
                lid, hops = ahead_of.get(lid, ""), hops + 1
            if past:
                asks.append((i, past, front, end))
        rooms = self.rooms(st, {a[1] for a in asks}) if asks else {}
        now: set[str] = set()
        out = red
        for i, past, front, end in asks:
            room = rooms.get(past)
            if room is None:
                continue  # nobody waiting past the junction: room further on
            v = vids[i]
            if room - front >= brutto.get(v, DEFAULT_BRUTTO_M):
                continue
            speed, decel = float(st.speed_mps[int(rows[i])]), shape_of[v][2]
            # Too near to stop jmStoplineGap before the line at its decel: it drives on.
            # SUMO keeps the request only nearer than brakeGap - tau v, but its drivers then
            # brake harder than decel; ours would count emergency brakings (1164: 1 -> 6-9).
            if v not in self.held and (
                float(brake_gap(np.float64(speed), decel, self.dt)) > end - STOPLINE_GAP_M
            ):
                continue
            now.add(v)
            if out is red:
                out = np.array(red, dtype=float)
            out[i] = end
        # Only the cars asked about now are decided: a call for some of them (the first
        # sight's observation of new drivers alone, ``DriverObserve.first_sight``) keeps the
        # others' holds, which it used to drop (a held car then faced the brake check again
        # in the same step); a car gone from the road is forgotten.
        asked = set(vids)
        self.held = {v for v in self.held if v in index and v not in asked} | now
        return out

"""What a deployment's driven vehicle on a section sees, from SUMO's state read once per
step (``sumo.states.VehicleStates``): the section env's observation
(``env.section_observations.section_observations``) with SUMO's own leader, and what the safety
layer needs (``deploy.drivers.safety_cap``). Vectorised over the driven vehicles: per
vehicle only dictionary look-ups in Python.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from macromicro_sumo.env.driver_tau import with_tau
from macromicro_sumo.env.observed_drivers import scale_limits
from macromicro_sumo.road.leaders import bumper_gap_m, nearer_standing
from macromicro_sumo.road.physics import (
    LEADER_COLUMN,
    LIMIT_COLUMN,
    NEXT_LIMIT_COLUMN,
    OBSERVATION_FEATURES,
    count_nonzero,
    has_lookahead,
    observes_gap,
    set_own_features,
)
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section

try:  # road/kernels.c, where setup.py built it (``observe_rows``' leader columns)
    from macromicro_sumo.road import kernels
except ImportError:  # not built: numpy's form, the same values
    kernels = None
from macromicro_sumo.sumo.reads import codes as lookup
from macromicro_sumo.sumo.reads import leader_codes
from macromicro_sumo.sumo.states import VehicleStates

STOP_DECEL_MPS2 = 9.0  # a standing "leader" (stop line, lane end) never brakes: any value
STANDING = (0.0, 0.0, STOP_DECEL_MPS2)  # (length, minGap, decel) of a standing leader


def _const(value: float, dtype: type = np.float64) -> np.ndarray:
    """A read-only numpy 0-d array: as an operand or a value written, what the Python
    scalar gives, without numpy 2.4's conversion of it each call (~0.3 us of a ~0.7 us
    comparison at 42 rows, measured; each microsecond between SUMO's steps also costs
    SUMO's step about as much again, stop 43)."""
    out = np.array(value, dtype=dtype)
    out.flags.writeable = False
    return out


_NO_GAP, _STOP_DECEL, _INF = _const(NO_LEADER_GAP_M), _const(STOP_DECEL_MPS2), _const(np.inf)
_ZERO = _const(0.0)
_ROW_0, _NO_INDEX = _const(0, np.int64), _const(-1, np.int64)


class Table:
    """Rows of a small table looked up by key with numpy: each key holds the code of a
    row, each column is a 1-D array (``cols``); a key not in it gets row 0, ``missing``.
    Columns, not one 2-D array: a take of a row per vehicle from a 2-D array costs ~6 us
    a call, from a column ~0.2 (numpy 2.4, 45 rows; measured)."""

    def __init__(self, missing: tuple[float, ...]) -> None:
        self.code: dict[str, int] = {}
        self.rows: list[tuple[float, ...]] = [missing]
        self.cols = self._columns()

    def _columns(self) -> tuple[np.ndarray, ...]:
        return tuple(np.array(c, dtype=float) for c in zip(*self.rows, strict=True))

    @classmethod
    def of_rows(cls, rows: dict[str, tuple], missing: tuple[float, ...]) -> Table:
        """A table with a row per key."""
        table = cls(missing)
        table.code = {key: i + 1 for i, key in enumerate(rows)}
        table.rows += list(rows.values())
        table.cols = table._columns()
        return table

    def add_row(self, row: tuple) -> int:
        """A new row; its code."""
        self.rows.append(row)
        self.cols = self._columns()
        return len(self.rows) - 1

    def codes(self, keys: list[str]) -> np.ndarray:
        """The codes of ``keys`` (0: missing)."""
        return lookup(self.code, keys, 0)


class LaneTable(Table):
    """``section.lanes`` with what the observation needs of each lane, tabulated once per
    run: per lane (edge, lane index, arc of its start, arc per lane metre, its speed limit,
    the look-ahead's next limit and where the next edge starts: ``Section.lookahead`` is
    a function of the lane alone, apart from the vehicle's arc)."""

    def __init__(self, sec: Section) -> None:
        super().__init__((np.nan,) * 7)
        self.closed, self.length_m = bool(sec.closed), float(sec.length_m)
        if sec.lanes:
            base = np.array(list(sec.lanes.values()), dtype=float).reshape(-1, 4)
            edge, lane = base[:, 0].astype(np.int64), base[:, 1].astype(np.int64)
            limit = sec.limits_mps[edge, np.minimum(lane, sec.n_lanes[edge] - 1)]
            # The look-ahead at the lane's start (``Section.lookahead``, the envs' own): its
            # distance is ``start - arc`` for any arc (on a loop ``start - arc mod length``),
            # its next limit the lane's.
            arc0 = sec.wrap(base[:, 2])
            next_limit, ahead = sec.lookahead(lane, arc0, edge, limit)
            start = ahead + arc0
            rows = np.column_stack([base, limit, next_limit, start])
            self.code = {key: i + 1 for i, key in enumerate(sec.lanes)}
            self.rows += [tuple(r) for r in rows.tolist()]
            self.cols = self._columns()
        (_, _, self.arc0_m, self.arc_per_m, self.limit_mps, self.next_limit_mps,
         self.next_start_m) = self.cols  # fmt: skip
        self._obs_rows: dict[str, np.ndarray] = {}
        self._driven = np.full(1, -1, dtype=np.int64)
        self.order = np.arange(1)

    def obs_rows(self, observation: str) -> np.ndarray:
        """(rows, F) per lane code: ``policy.observation``'s columns that are the lane's
        alone (its limit; with a look-ahead the next limit, and where the next edge starts
        in the distance's column), 0 in the others; one take gives a step's observations
        these columns. Built once per run and layout."""
        if (tab := self._obs_rows.get(observation)) is None:
            tab = np.zeros((len(self.rows), len(OBSERVATION_FEATURES[observation])))
            tab[:, LIMIT_COLUMN] = self.limit_mps
            if has_lookahead(observation):
                tab[:, NEXT_LIMIT_COLUMN] = self.next_limit_mps
                tab[:, NEXT_LIMIT_COLUMN + 1] = self.next_start_m
            self._obs_rows[observation] = tab
        return tab

    def driven_rows(self, n_rows: int) -> np.ndarray:
        """A buffer of -1 longer than ``n_rows`` (a step's vehicles), kept between steps:
        the caller writes the driven vehicles' indices at their rows, reads, and writes -1
        back; its last entry, which row -1 reads, stays -1. ``order`` grows with it: 0, 1,
        ... as long, the indices to write (a slice of it, not an ``arange`` a step)."""
        if len(self._driven) <= n_rows:
            self._driven = np.full(2 * n_rows + 1, -1, dtype=np.int64)
            self.order = np.arange(len(self._driven))
        return self._driven


def observe_rows(
    lanes: LaneTable,
    observation: str,
    vids: list[str],
    rows: np.ndarray,
    lane_ids: list[str],
    st: VehicleStates,
    leaders: list[tuple[str, float]],
    shapes: Table,
    stop_m: np.ndarray,
    driver_speeds: Callable[[list[str], np.ndarray], np.ndarray] | None = None,
    lane_codes: np.ndarray | None = None,
    stop_gap_m: float | None = None,
    driver_taus: Callable[[list[str], np.ndarray], np.ndarray] | None = None,
    turns: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Observations (V, obs_dim) of driven vehicles ``vids`` (rows ``rows`` of ``st``, on
    lanes ``lane_ids``), as the section env defines them, the leader SUMO's (``leaders``:
    ``Simulation.leaders``): front-to-front spacing = SUMO's gap + own minGap + leader's
    length (a gap layout: the leader column is that less the leader's length, SUMO's vType
    length; a standing leader's the own, ``road.leaders.bumper_gap_m``); ``stop_m``:
    SUMO's gap from each front to its stop at a red light or the end of a lane the vehicle
    must leave (``road.leaders.stop_distance_m``; inf: none), a standing
    leader there when nearer than the leader (``road.leaders.nearer_standing``, as the envs
    see it). ``lanes``: the section's ``LaneTable``; ``shapes``: vehicle -> (length,
    minGap, decel), ``STANDING`` where missing; ``driver_speeds``: each driver's desired-speed factor on the limits it
    observes, from the vehicles and their observations with unscaled limits
    (``policy.driver_speed``; None: 1); ``lane_codes``: ``lanes.codes(lane_ids)`` if known;
    ``stop_gap_m``: the bumper gap the policy stops at (its prior's fitted minGap,
    ``deploy.stage.policy_batch``; the driver gives it only with safety "none", where no
    layer holds the vType's minGap; None: the leader column as above): a vehicle
    whose own minGap is larger observes its leader, a standing one included, that much
    nearer (``min_gap_deficit_m``), so that the policy's stop falls at its own minGap, not
    inside it, where SUMO counts a collision (its collisionMinGapFactor 1; Stage II's
    replay counts only an overlap). ``driver_taus``: each driver's own tau [s] from the
    vehicles and their observations (``policy.driver_follow``, ``env.driver_tau.DriverTaus``
    and its hand-over), appended as a trailing column (None: no column). ``turns``:
    (indices, the turn's limit, the arc of its stop line) of turners before the line where
    they leave the section (``deploy.turns`` "limit", ``deploy.turns.Turns.ahead``): their
    look-ahead is that limit at that line, not the next section edge's (None: none).
    Also returns SUMO's gap to what the vehicle sees ahead, that leader's decel, and its
    index in ``vids`` where it is a driven vehicle (-1: none, not driven, or a standing
    leader): the safety layer knows a driven leader's next speed, its command.

    The fixed cost per call is what a step of a small deployment pays (numpy's ~0.3-1 us a
    call): one look-up of each table column for all vehicles and leaders, the standing
    leaders' columns only where one is nearer (``scripts/bench_deploy.py``)."""
    n = len(vids)
    if not n:
        obs = np.empty((0, len(OBSERVATION_FEATURES[observation]) + (driver_taus is not None)))
        return obs, np.empty(0), np.empty(0), np.empty(0, dtype=np.int64)
    codes = lanes.codes(lane_ids) if lane_codes is None else lane_codes
    # The lanes' own columns in one take (a fresh array): the limits, and where the next
    # edge starts in the distance's column.
    obs = lanes.obs_rows(observation).take(codes, axis=0)  # a third of [codes]'s cost
    if turns is not None and turns[0].size and has_lookahead(observation):
        obs[turns[0], NEXT_LIMIT_COLUMN] = turns[1]
        obs[turns[0], NEXT_LIMIT_COLUMN + 1] = turns[2]  # the line, less the arc below
    speed = None  # the driven vehicles' speeds, taken where numpy's path needs them
    # SUMO's gaps; the leader SUMO sees, if it is on the road (in ``st``), row -1 otherwise;
    # own and leaders' shapes (own first). A leader off the road may have a shape: what
    # reads it (spacing, decel) is overwritten below where there is no leader.
    gap, lead_row, shape = leader_codes(leaders, st.index, shapes.code, vids)
    length_m, min_gap_m, decel_mps2 = shapes.cols
    sumo_gap, bumper = gap, None
    # A driven leader's index in ``vids``: a row of ``st`` -> its index, -1 elsewhere
    # (a buffer of -1 kept per run; its last entry answers row -1, no leader).
    driven = lanes.driven_rows(len(st.ids))
    if kernels is not None:  # the compiled pass (road/kernels.c): the same values
        cols, lead_index, ok = np.empty((7, n)), np.empty(n, np.int64), np.empty(n, bool)
        args = (gap, lead_row, rows, shape, st.speed_mps, length_m, min_gap_m, decel_mps2)
        outs = (cols, lead_index, ok)
        if kernels.leader_columns(*args, driven, NO_LEADER_GAP_M, STOP_DECEL_MPS2, *outs):
            spacing, lead_v, lead_decel, length, min_gap, lead_length, bumper = cols
    if bumper is None:
        speed = st.speed_mps[rows]
        has = lead_row >= _ROW_0
        lengths = length_m[shape]
        length, lead_length = lengths[:n], lengths[n:]
        min_gap = min_gap_m[shape[:n]]
        # Fresh arrays overwritten where there is no leader (masked writes: a third of
        # np.where's cost a call).
        spacing = gap + min_gap
        spacing += lead_length
        ok = has & (spacing < _NO_GAP)
        # Those without one, as indices: a write by index costs ~2/3 of a masked one (five).
        none = (~ok).nonzero()[0]
        lead_v = st.speed_mps[lead_row]
        lead_v[none] = speed[none]  # delta_v 0 without a leader
        spacing[none] = _NO_GAP
        sumo_gap[none] = _NO_GAP
        lead_decel = decel_mps2[shape[n:]]
        lead_decel[none] = _STOP_DECEL
        driven[rows] = lanes.order[:n]
        lead_index = driven[lead_row]
        driven[rows] = _NO_INDEX
        lead_index[none] = _NO_INDEX
    # A red light, or the end of a lane the vehicle must leave: a standing leader there.
    # None ahead of anyone (inf or NaN: nothing can be nearer; every step of Bremen's
    # section): nearer_standing's five array calls not made.
    closer = None
    if count_nonzero(stop_m < _INF):
        closer = nearer_standing(spacing, stop_m, length, min_gap, lead_length)
    if any_closer := closer is not None and bool(count_nonzero(closer)):
        lead_v[closer] = 0.0
        np.copyto(sumo_gap, np.maximum(stop_m, _ZERO), where=closer)
        lead_decel[closer] = STOP_DECEL_MPS2
        lead_index[closer] = -1
    ahead = has_lookahead(observation)  # the distance: the next edge's start - the arc
    # The compiled pass on an open section (road/kernels.c): the same values, numpy's ~10
    # calls in one.
    args = (rows, codes, st.speed_mps, st.pos_m, lead_v, lanes.arc_per_m, lanes.arc0_m, ahead)
    own = getattr(kernels, "own_columns", None)  # None: not built, or built before it
    if own is None or lanes.closed or not own(obs, *args):
        speed = st.speed_mps[rows] if speed is None else speed
        obs[:, 0] = speed
        obs[:, 3] = speed - lead_v
        if ahead:
            arc = lanes.arc_per_m[codes]
            arc *= st.pos_m[rows]
            arc += lanes.arc0_m[codes]  # arc0 + pos x arc_per_m: + and x commute exactly
            obs[:, 5] -= np.mod(arc, lanes.length_m) if lanes.closed else arc
    set_own_features(obs, observation, length)
    if observes_gap(observation):  # ``set_leader_gap``'s gap, from the spacing at hand
        # no leader: NO_LEADER_GAP_M stays, whatever the length
        if any_closer:
            np.copyto(lead_length, length, where=closer)
            obs[:, LEADER_COLUMN] = bumper_gap_m(spacing, lead_length)
        else:  # ``bumper_gap_m``'s values: spacing < NO_LEADER_GAP_M exactly where ``ok``
            if bumper is None:  # the kernel's where it ran
                bumper = spacing - lead_length
                bumper[none] = _NO_GAP
            obs[:, LEADER_COLUMN] = bumper
    else:
        obs[:, LEADER_COLUMN] = spacing
    if stop_gap_m is not None:
        deficit = min_gap_deficit_m(min_gap, stop_gap_m)
        lead = obs[:, LEADER_COLUMN]  # a view: no leader keeps NO_LEADER_GAP_M
        np.subtract(lead, deficit, out=lead, where=ok if closer is None else ok | closer)
    if driver_speeds is not None:
        scale_limits(obs, driver_speeds(vids, obs))
    if driver_taus is not None:  # policy.driver_follow: each driver's own tau, last
        obs = with_tau(obs, driver_taus(vids, obs))
    return obs, sumo_gap, lead_decel, lead_index


def min_gap_deficit_m(min_gap_m: np.ndarray, stop_gap_m: float) -> np.ndarray:
    """Per vehicle, how much its own minGap ``min_gap_m`` exceeds the gap its policy stops
    at ``stop_gap_m`` (0 where it does not): what ``observe_rows`` takes off the leader
    column. On drawn net 501 the Krauss prior's fitted minGap, 2.458 m, is a fleet's (cars
    and trucks 2.5 m, IDM cars 2.0): without the layer, cars and trucks crept at 0.01-0.08
    m/s into the minGap of the standing car ahead, all 475 collision events of 4 runs."""
    return np.maximum(min_gap_m - stop_gap_m, 0.0)


def states_of(states: dict[str, tuple[str, float, float, float]]) -> VehicleStates:
    """``VehicleStates`` from a {vehicle: (lane ID, lane position, speed, acceleration)}
    dictionary (``Simulation.read_lane_states``'s, as the demand env reads them)."""
    ids = tuple(states)
    n = len(ids)
    vals = list(states.values())
    return VehicleStates(
        ids,
        [s[0] for s in vals],
        np.fromiter((s[1] for s in vals), float, n),
        np.fromiter((s[2] for s in vals), float, n),
        np.fromiter((s[3] for s in vals), float, n),
    )

"""The deployment's safety layer (``deploy.safety = "sumo"``): what a speed-commanding
driver (``deploy.drivers``) does to a method's commands before SUMO applies them, so that
no command, however poor or adversarial, makes a vehicle collide or block the road.

* Each command is capped at SUMO's Krauss safe speed behind the leader the vehicle
  observes (``road.physics.safe_speed``: the leader's braking at max(b, b_l), as SUMO's),
  the vehicle's own braking b its vType's decel or, with ``deploy.safety_brake =
  "matched"``, at least its moving leader's (``planned_decel``); a vehicle taken over from
  its own model starts from the braking its arrival gap supports, at most its leader's,
  and returns to that b gradually (``BrakeHandover``);
* a leader that is driven too is followed by its command, its known next speed
  (``behind_commands``), so one braking harder than its decel takes its followers along;
* the command is raised to a floor (``deploy.safety_floor_share`` of the lane's limit,
  default ``FLOOR_SHARE``, at most the safe speed) so that no vehicle is held standing where
  nothing ahead asks for it: any command below it, or, with ``deploy.safety_floor_on =
  "standing"``, only a vehicle's slower than ``STANDING_BELOW_MPS`` (``"auto"``: one of the
  two, chosen by the stage before any driver starts, ``deploy.floor_choice``; a driver
  built without that choice floors all); with ``deploy.safety_floor_reaction_s`` a standing
  vehicle's floor is at most its safe speed with that reaction time
  (``reaction_safe_speed``), so that a queue starts about as late as SUMO's drivers;
* ``speed_commands`` is the one command rule of the ring's and the sections' speed drivers
  (``deploy.drivers``): v + a dt of the batched action, a in the scenario's bounds and, by
  default, braking no harder than the layer plans the vehicle's stop with
  (``command_brake``), through this layer where ``deploy.safety = "sumo"``, and, with or without it, at most the
  vehicle's vType maxSpeed (its physics, not safety: SUMO does not impose it on a command
  under these speed modes).

Pure numpy: tested without SUMO and, through the drivers, with it
(``tests/deploy/test_safety.py``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from macromicro_sumo.deploy.observe import STOP_DECEL_MPS2
from macromicro_sumo.deploy.population import ActionBatch, DriveStats
from macromicro_sumo.road.physics import brake_gap, constants, safe_speed, step_constants
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.road.vtype import accel_limit, command_speeds
from macromicro_sumo.scenario.stages import DeployConfig

# Speed modes of speed-commanded vehicles (SUMO's bits, ``sumo.simulation``). "none" applies
# the command exactly (32: no safe speed, no accel/decel limits, no right of way, no braking
# for red lights). "sumo" (24) keeps right of way and red lights, and the driver caps each
# command at SUMO's Krauss safe speed behind the leader it observes (``safe_speed``):
# SUMO's own safe-speed bit is left off because it also caps at the lane's limit times the
# speed factor and at its model's choice (IDM's follow speed is its next speed), no safety.
SPEED_MODES = {"none": 32, "sumo": 24}
SAFETY_TOLERANCE_MPS = 0.01
# A driven leader commanded this much above the speed safe_speed assumed it brakes to
# (``behind_commands``) leaves its follower 5e-7 m more room at 0.5 s, a safe speed some
# 1e-7 m/s higher: far beyond safe_speed's rounding (~1e-13 m/s) [m/s].
BEHIND_MARGIN_MPS = 1e-6
# The safety layer's floor, the default of ``deploy.safety_floor_share``: a command is
# raised to this share of the lane's speed limit (capped at the safe speed and at the
# vehicle's acceleration) so that a policy cannot stop a vehicle where nothing ahead asks
# for it: Bremen's policy braked cars to a standstill on the free road (leader 80 m ahead
# and faster) and held them there, until SUMO teleported them after 300 s (93 teleports in
# a run). A fifth: 8.9 m/s at Bremen's 44.4 m/s, below 1.1% of the ground truth's
# vehicle-steps, all of them queued at the merge.
FLOOR_SHARE: float = DeployConfig.safety_floor_share
# ``deploy.safety_floor_on = "standing"``: the floor raises only a vehicle slower than this
# [m/s], one held standing (or crawling) where nothing ahead asks for it. The default
# ("all") raised 70% of the slow and queued steps of game/ramp's policy, where it brakes
# (training has no floor), and the ramp ran 1.9 m/s slow (docs/deploy-log.md, "Safety layer
# strictness (stop 29)").
STANDING_BELOW_MPS = 1.0
# ``deploy.safety_brake``: the braking the layer plans a driven vehicle to stop with (the
# config's choices, one definition).
SAFETY_BRAKES: tuple[str, ...] = DeployConfig.__dataclass_fields__["safety_brake"].metadata[
    "choices"
]
# How fast the braking the layer plans a new driver's stop with returns from the braking its
# arrival gap supports to its own (``BrakeHandover``) [m/s^2 per s]. At 20 m/s the layer's
# safe speed falls by about v^2 / (2 b (v + b dt)), 3 m/s per m/s^2 of b at b = 3.0: 0.5
# m/s^2/s asks some 1.5 m/s^2 of braking more, half an IDM car's decel (the tau hand-over's
# figure, ``env.driver_tau.HANDOVER_RATE_S_PER_S``). Drawn 502, prior alone, all 4 runs:
# 0.25 / 0.5 / 1.0 / 2.0 m/s^2/s gave 19 / 18 / 109 / 132 emergency brakings against 74
# without it (a faster return brakes the driver by the layer's own fall), speed RMSE
# 1.106 / 1.110 / 1.115 / 1.113 m/s against 1.112.
HANDOVER_DECEL_RATE_MPS2_PER_S = 0.5
# The per-step operands above as read-only 0-d arrays made once (``road.physics.constants``):
# a Python float costs a numpy call a conversion and a weak-scalar promotion, some 0.3 us of
# ~1 us at ~40 rows; on float64 arrays (the deployment's) the values are the same to the bit.
_NO_LEADER_GAP, _INF, _ZERO, _TOLERANCE, _BEHIND_MARGIN, _STANDING_BELOW = constants(
    NO_LEADER_GAP_M, np.inf, 0.0, SAFETY_TOLERANCE_MPS, BEHIND_MARGIN_MPS, STANDING_BELOW_MPS
)
_NO_LEAD = np.zeros((), dtype=np.int64)  # ``lead``'s 0: the first index, -1 is none
_NO_LEAD.flags.writeable = False


def planned_decel(decel: np.ndarray, lead_decel: np.ndarray, brake: str) -> np.ndarray:
    """The braking b [m/s^2] the safety layer plans each driven vehicle's stop with, of
    its vType's decel ``decel`` and the decel of what it sees ahead ``lead_decel``
    (``STOP_DECEL_MPS2``: nothing, a red light or a lane end): "own", its decel;
    "matched", at least its leader's, max(b, b_l), where that leader is a vehicle.

    With "own" the layer is stricter than SUMO's own IDM drivers: IDM's decel is its
    comfortable braking, which SUMO's IDM exceeds where it must (up to its emergencyDecel,
    9 m/s^2 for a passenger car), while the layer plans the stop at it: an IDM car (b =
    3.0) behind a Krauss car (b_l = 4.5) must stop at 3.0 behind a leader stopping at
    4.5. On drawn network 300's ground truth the layer would have lowered 21.4% of SUMO's
    IDM cars' own next speeds behind Krauss cars (by 0.77 m/s on average), none with
    "matched"; never a Krauss car's, with either (their tau of 1 s asks more than the
    layer's one step). "matched" asks a driven car to brake no harder than the vehicle
    ahead of it may, below any car's emergency braking; a standing obstacle does not brake
    (its ``STOP_DECEL_MPS2`` is a placeholder), so there the vehicle's own decel holds.
    The stop condition stays SUMO's (``safe_speed``). Not the default: deployed, it was
    not better (docs/deploy-log.md, "Safety layer strictness (stop 29)")."""
    if brake == "own":
        return decel
    return np.where(lead_decel < STOP_DECEL_MPS2, np.maximum(decel, lead_decel), decel)


def supported_decel(
    gap: np.ndarray,
    lead_speed: np.ndarray,
    speed: np.ndarray,
    decel: np.ndarray,
    lead_decel: np.ndarray,
    dt_s: float,
) -> np.ndarray:
    """Per vehicle, the least braking b [m/s^2] the layer may plan its stop with
    (``safe_speed``, ``gap``: SUMO's gap to what it sees ahead, ``NO_LEADER_GAP_M`` or
    more: none) at which its safe speed is at least its ``speed``: ``decel`` where that
    holds at it (and where nothing is ahead), else the least b up to "matched"'s
    (``planned_decel``: its moving leader's decel b_l; a standing obstacle: ``decel``), at
    most that (none: no b would do). Below b_l the leader's braking is planned at
    max(b, b_l) = b_l, and the safe speed is at least v where v dt + brake_gap(v, b) is at
    most the room, gap + brake_gap(v_l, b_l): brake_gap falls with b, linear between the
    b = v / (n dt) at which it is dt v (n - 1) / 2 (n Euler steps to stop), so the least
    b is on the piece of the least such n, solved there (a closed form: the bisection it
    replaces cost some 130 us a new driver). Within rounding of the speed: at most 7e-15
    m/s below it over 20,390 seeded states that need more than the vType's decel."""
    lo = np.asarray(decel, dtype=float)
    short = _beyond_own(gap, lo, lead_decel)
    # Where no leader can hold more than the vehicle's decel (every step on Bremen), the
    # safe-speed test on no vehicles is skipped: some 15 numpy calls on empty arrays.
    if not short.any():
        return lo.copy()
    return _supported(short, gap, lead_speed, speed, lo, lead_decel, dt_s)


def _beyond_own(gap: np.ndarray, lo: np.ndarray, lead_decel: np.ndarray) -> np.ndarray:
    """``supported_decel``'s vehicles that may need more than their decel ``lo``: a leader
    (``gap`` below ``NO_LEADER_GAP_M``) whose braking "matched" plans above ``lo``."""
    return (gap < NO_LEADER_GAP_M) & (planned_decel(lo, lead_decel, "matched") > lo)


def _supported(
    short: np.ndarray,
    gap: np.ndarray,
    lead_speed: np.ndarray,
    speed: np.ndarray,
    lo: np.ndarray,
    lead_decel: np.ndarray,
    dt_s: float,
) -> np.ndarray:
    """``supported_decel`` where ``short`` (``_beyond_own``) has a vehicle (``short`` is overwritten)."""
    hi = planned_decel(lo, lead_decel, "matched")
    short[short] = (
        safe_speed(gap[short], lead_speed[short], lo[short], lead_decel[short], dt_s) < speed[short]
    )
    out = lo.copy()
    if not short.any():
        return out
    v = speed[short]
    spare = (
        np.maximum(gap[short], 0.0)
        + brake_gap(lead_speed[short], lead_decel[short], dt_s)
        - v * dt_s
    )
    n = np.maximum(np.floor(2.0 * spare / (dt_s * v)) + 1.0, 1.0)
    b = (n * v - spare / dt_s) * 2.0 / (dt_s * n * (n + 1.0))
    out[short] = np.clip(b, lo[short], hi[short])
    return out


class BrakeHandover:
    """The layer's braking for drivers taken over from their own models
    (``deploy.drivers``, where ``deploy.safety = "sumo"``): at a vehicle's first driven
    step its planned braking starts at the least one its arrival state supports
    (``supported_decel``: its safe speed at least its speed), at most its moving leader's,
    and falls back to the layer's own (``planned_decel``) at
    ``HANDOVER_DECEL_RATE_MPS2_PER_S``; where the arrival state supports its own nothing
    changes. Called per step with the driven vehicles, returns their planned brakings.

    Why: a vehicle arrives at the gap its own model kept. SUMO's IDM cars (decel 3.0, tau
    1.2 s) keep gaps behind Krauss cars (decel 4.5) at which the layer's safe speed, its
    stop planned at 3.0 behind a leader's at 4.5, is below their speed (on drawn 502 by a
    median 1.64 m/s, up to 2.17, against 1.5 in a 0.5 s step at 3.0 m/s^2): the
    layer braked them at more than their decel on their first driven step. On drawn 502
    (prior alone, all 4 runs) 65 of the 74 emergency brakings were that: every one an IDM
    car behind a Krauss car, 16-26 m/s at gaps of 19-51 m, supported at b of 3.41-3.72
    m/s^2; the truth had 1."""

    def __init__(self, dt_s: float) -> None:
        self.dt_s = float(dt_s)
        # Per slot (``deploy.slots.VehicleSlots``: one per vehicle met, never reused): its
        # planned braking at its hand-over and that step, and the step its ramp ends (-inf:
        # none; +inf: the vehicle is not met yet, so that one read of the driven vehicles'
        # slots finds both the new drivers and the ramps). A step with no new driver and no
        # ramp costs a gather, a comparison and a nonzero (a set of the driven ids a step
        # cost ~30 us on Bremen, a tenth of the driver's time; a separate "met" array, its
        # slots.max() and its reads, ~8 numpy calls a step).
        self._start = np.zeros((0, 2))
        self._end = np.zeros(0)

    def _grow(self, size: int) -> None:
        n = max(size, 2 * len(self._end), 64)
        self._start = np.concatenate([self._start, np.zeros((n - len(self._start), 2))])
        self._end = np.concatenate([self._end, np.full(n - len(self._end), np.inf)])

    def __call__(
        self,
        slots: np.ndarray,
        decel: np.ndarray,
        lead_decel: np.ndarray,
        gap: np.ndarray,
        speed: np.ndarray,
        lead_speed: np.ndarray,
        step: int,
    ) -> np.ndarray:
        """The planned braking [m/s^2] of the driven vehicles in ``slots`` at ``step``:
        ``decel`` (``planned_decel``'s) but where a hand-over holds more, from their state
        now (SUMO's ``gap`` to what each sees ahead, its ``speed``, its leader's speed and
        decel) where a vehicle is met for the first time."""
        rate = HANDOVER_DECEL_RATE_MPS2_PER_S * self.dt_s
        try:
            end = self._end[slots]
        except IndexError:  # a slot beyond the arrays: grown (slots are never negative)
            self._grow(int(slots.max()) + 1)
            end = self._end[slots]
        on = (end >= step).nonzero()[0]  # new drivers (+inf) and ramps
        if not on.size:
            return decel
        fresh = end[on] == np.inf
        if fresh.any():
            new = on[fresh]
            self._end[slots[new]] = -np.inf
            # supported_decel's, its state read only where a leader may ask more (no new
            # driver's on Bremen: there each step with one costs a few numpy calls).
            lo, ahead, lead_b = decel[new], gap[new], lead_decel[new]
            short = _beyond_own(ahead, lo, lead_b)
            got = ramp = None
            if short.any():
                got = _supported(short, ahead, lead_speed[new], speed[new], lo, lead_b, self.dt_s)
                ramp = got > lo
            if ramp is not None and ramp.any():
                s, b = slots[new[ramp]], got[ramp]
                self._start[s, 0], self._start[s, 1] = b, step
                self._end[s] = step + np.ceil((b - lo[ramp]) / rate)
                on = (self._end[slots] >= step).nonzero()[0]
            else:
                on = on[~fresh]
            if not on.size:
                return decel
        start = self._start[slots[on]]
        out = decel.copy()
        out[on] = np.maximum(decel[on], start[:, 0] - rate * (step - start[:, 1]))
        return out


def leader_safe_speed(
    obs: np.ndarray,
    gap: np.ndarray,
    decel: np.ndarray,
    lead_decel: np.ndarray,
    dt_s: float,
    lead_speed: np.ndarray | None = None,
) -> np.ndarray:
    """Per vehicle, ``safe_speed`` [m/s] behind the leader it observes (``gap``: SUMO's gap
    to it, ``NO_LEADER_GAP_M`` or more: none, inf; its speed obs[:, 0] - obs[:, 3]; a
    standing leader at a stop line or lane end included): the cap of ``safety_cap``,
    computed once a step and shared with a driver's merge handling (``deploy.drivers``).
    ``lead_speed``: obs[:, 0] - obs[:, 3] if computed already."""
    if lead_speed is None:
        lead_speed = obs[:, 0] - obs[:, 3]
    safe = safe_speed(gap, lead_speed, decel, lead_decel, dt_s)
    safe[~(gap < _NO_LEADER_GAP)] = _INF  # no leader: no cap (safe_speed's is fresh)
    return safe


def reaction_safe_speed(
    gap: np.ndarray,
    lead_speed: np.ndarray,
    decel: np.ndarray | float,
    lead_decel: np.ndarray | float,
    dt_s: float,
    reaction_s: float,
) -> np.ndarray:
    """SUMO's Krauss safe speed [m/s] with a reaction time ``reaction_s`` (its headway, the
    vType's tau) instead of one step: the fastest v that, held ``reaction_s`` and braked at
    b in Euler steps after it, stops in gap + brake_gap(v_l, max(b, b_l)) (``gap``: SUMO's,
    ``NO_LEADER_GAP_M`` or more: none, inf): ``maximumSafeStopSpeedEuler`` with headway t;
    with t = dt, ``safe_speed``'s. The floor's cap of a standing vehicle (slower than
    ``STANDING_BELOW_MPS``) with ``deploy.safety_floor_reaction_s``: with one step a
    standing queue's car is lifted to room / dt the step after its leader moves (drawn 528:
    0.53 s a car, the truth's 0.84-0.97 s), with a tau of 1 s to half (0.73-0.81 s a car).
    A moving vehicle's floor keeps the one step: all of them with the reaction, drawn 565's
    policy, slow already, lost 0.09 m/s of speed RMSE (standing only: gained 0.01)."""
    lead_b = np.maximum(decel, lead_decel)
    room = np.maximum(gap, 0.0) + brake_gap(lead_speed, lead_b, dt_s)
    t, s = float(reaction_s), float(dt_s)
    b = np.multiply(decel, s)  # the speed lost per step braking
    # The most braking steps n whose distance h(n) after the reaction fits the room, then
    # the speed above n b that fills the rest over n steps and the reaction.
    n = np.floor(0.5 - (t - 0.5 * np.sqrt(s * s + 4.0 * (s * (2.0 * room / b - t) + t * t))) / s)
    n = np.maximum(n, 0.0)
    h = 0.5 * n * (n - 1.0) * b * s + n * b * t
    out = n * b + (room - h) / (n * s + t)
    out[~(np.asarray(gap) < NO_LEADER_GAP_M)] = np.inf
    return out


def safety_cap(
    cmd: np.ndarray,
    obs: np.ndarray,
    gap: np.ndarray,
    decel: np.ndarray,
    lead_decel: np.ndarray,
    lead: np.ndarray,
    dt_s: float,
    a_max_mps2: np.ndarray | float,
    floor_share: np.ndarray | float,
    safe: np.ndarray | None = None,
    lead_speed: np.ndarray | None = None,
    vmax: np.ndarray | float = np.inf,
    floor_safe: np.ndarray | None = None,
) -> tuple[np.ndarray, int, int]:
    """Speed commands ``cmd`` [m/s] made safe: capped at ``safe_speed`` behind each
    vehicle's observed leader (``gap``: SUMO's gap to it, ``NO_LEADER_GAP_M`` or more:
    none, no cap; its speed obs[:, 0] - obs[:, 3]), raised to the floor where nothing
    ahead asks for less (``floor_share`` of the lane's limit obs[:, 1], per vehicle or one
    for all; 0: none), and capped behind the command of a leader that
    is driven too (``lead``: its index in ``cmd``, -1: none; ``behind_commands``).
    ``safe``: ``leader_safe_speed`` of these inputs if computed already; ``lead_speed``:
    obs[:, 0] - obs[:, 3] if computed already; ``vmax``: the vehicles' maxSpeed [m/s], which
    the floor does not exceed (the commands are at most it already: ``speed_commands``);
    ``a_max_mps2``: the acceleration the floor may lift a vehicle by, one for all or per
    vehicle (the bound, at most the vType's accel: ``speed_commands``); ``floor_safe``:
    the safe speed the floor is capped at where it is not ``safe`` (at most it:
    ``reaction_safe_speed``, ``deploy.safety_floor_reaction_s``). Returns (commands,
    how many the layer lowered, how many it raised), each by more than
    ``SAFETY_TOLERANCE_MPS``."""
    if lead_speed is None:
        lead_speed = obs[:, 0] - obs[:, 3]
    if safe is None:
        safe = leader_safe_speed(obs, gap, decel, lead_decel, dt_s, lead_speed)
    # The road kept open: never below a share of the lane's limit unless what is ahead
    # (the safe speed) asks for it, and no faster than the vehicle may accelerate to it.
    under = safe if floor_safe is None else np.minimum(safe, floor_safe)
    floor = np.minimum(under, np.minimum(obs[:, 0] + a_max_mps2 * dt_s, floor_share * obs[:, 1]))
    floor = np.minimum(floor, vmax)
    capped = np.minimum(cmd, safe)
    raised = int(np.count_nonzero(floor > capped + _TOLERANCE))
    out = behind_commands(np.maximum(capped, floor), gap, lead, decel, lead_decel, dt_s, lead_speed)
    return out, int(np.count_nonzero(out < cmd - _TOLERANCE)), raised


def behind_commands(
    cmd: np.ndarray,
    gap: np.ndarray,
    lead: np.ndarray,
    decel: np.ndarray,
    lead_decel: np.ndarray,
    dt_s: float,
    lead_speed: np.ndarray | None = None,
) -> np.ndarray:
    """``cmd`` [m/s] lowered where a driven leader's own command leaves less room than
    ``safe_speed`` assumed: it assumes the leader brakes at most at its decel, but a
    command may brake harder (a policy's bound below -decel, or the leader's own cap
    behind a leader that did). SUMO applies a command within the step (speed modes
    without the decel bit, checked: speeds after the step equal the commands), so the
    leader's next speed v_l' is known: from where both are after the step, the follower
    must stop behind it, ``safe_speed(gap + v_l' dt, v_l')``. A lowered command may in
    turn brake harder than assumed for its own follower: repeated until none changes
    (once per vehicle at most; on a ring of driven vehicles the chain may come round).

    ``lead_speed``: the leader speeds v_l ``safe_speed`` assumed, where each ``cmd`` is at
    most that safe speed (``safety_cap``'s): then only a leader commanded below
    max(v_l - max(b, b_l) dt, 0) + ``BEHIND_MARGIN_MPS`` can lower a command, and where
    none is the loop is skipped. One at or above it leaves at least the room assumed (its
    Euler braking from v_l is one step at v_l - max(b, b_l) dt and the braking from there;
    a leader slower than max(b, b_l) dt was assumed standing after the step), the margin
    far more than rounding: the same commands, some 25 numpy calls fewer a step."""
    led = lead >= _NO_LEAD
    if lead_speed is not None:
        # Over every vehicle, those without a driven leader masked out: fewer array calls a
        # step than gathering the others first (cmd[-1] stands in for no leader).
        brake = np.maximum(decel, lead_decel) * step_constants(dt_s)[0]
        least = np.maximum(lead_speed - brake, _ZERO) + _BEHIND_MARGIN
        if not np.count_nonzero(led & (cmd[lead] < least)):
            return cmd
    has = led.nonzero()[0]
    if not has.size:
        return cmd
    cmd = cmd.copy()
    room, ahead = np.maximum(gap[has], 0.0), lead[has]
    b, b_l = decel[has], lead_decel[has]
    for _ in range(len(has)):
        v_l = cmd[ahead]
        alt = safe_speed(room + v_l * dt_s, v_l, b, b_l, dt_s)
        lower = alt < cmd[has]
        if not lower.any():
            break
        cmd[has[lower]] = alt[lower]
    return cmd


def command_brake(a_min_mps2: float, decel: np.ndarray, brake: str) -> np.ndarray | float:
    """The least acceleration [m/s^2] a driven vehicle's command may ask before the safety
    layer (``deploy.command_brake``): "bounds", the scenario's lower bound ``a_min_mps2``;
    "decel" (the default), at least -``decel``, the braking the layer plans the vehicle's stop with
    (``planned_decel``: its vType's decel, ``decel_of``, but during a ``BrakeHandover``
    ramp or with ``deploy.safety_brake = "matched"``). The layer lowers a command further
    where what is ahead asks for it (``safety_cap``): a real emergency, kept.

    Why: the bound (-4.5 m/s^2 in the examples) is below an IDM car's decel (3.0) or a
    truck's (4.0); a policy braking at it is an emergency braking by SUMO's count, one a
    follower SUMO drives does not plan for, where nothing ahead asked for it. Drawn 501,
    all 4 runs, bounds -> decel: emergency brakings 458 -> 233, speed RMSE 3.32 -> 3.28
    m/s; with ``deploy.merge_reach = "occupation"`` 341 -> 191 and 2.53 -> 2.40; 0
    collisions and teleports; netgen_corridor, Bremen (decel 4.5, the bound) and drawn 502
    the same to the bit (their policies never braked beyond a decel)."""
    if brake == "bounds":
        return a_min_mps2
    return np.maximum(a_min_mps2, -decel)


# Per driven vehicle (SUMO's gap to what it sees ahead, its decel, that leader's decel, the
# leader's index among the driven or -1): what the safety layer needs, asked only with it.
LayerInputs = Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def speed_commands(
    sc,
    act: ActionBatch,
    safety: str,
    stats: DriveStats,
    obs: np.ndarray,
    layer: LayerInputs,
    cap: np.ndarray | None = None,
    safe: np.ndarray | None = None,
    lead_speed: np.ndarray | None = None,
    vmax: np.ndarray | float = np.inf,
    accel: np.ndarray | float = np.inf,
) -> np.ndarray:
    """Speed commands v' = max(0, v + a dt) [m/s] of the batched action ``act`` at
    observations ``obs`` (v in column 0, the lane's limit in column 1), a clipped to the
    scenario's bounds, through the safety layer (``deploy.safety.safety_cap``, floor
    ``deploy.safety_floor_share``, on the vehicles ``deploy.safety_floor_on`` names) where
    ``safety`` is "sumo", its actions counted in
    ``stats``: the one command rule of the ring's and the sections' speed drivers.
    ``cap``: speeds [m/s] the commands are lowered to before the layer (a merge's
    cooperative slow-down, ``deploy.drivers``; inf: none); ``safe``: the layer's safe
    speeds (``leader_safe_speed``) and obs[:, 0] - obs[:, 3] (``lead_speed``) where the
    driver computed them already. ``vmax``: each vehicle's vType maxSpeed [m/s], a bound of
    its physics, not of safety: every command is at most it, with or without the layer
    (SUMO imposes it only under the max-accel bit, which these speed modes leave off), and
    is not counted as the layer's action. ``accel``: each vehicle's vType accel [m/s^2],
    its physics too (SUMO's Krauss and IDM never accelerate harder): a is at most it, and
    so is the floor's reach (an inf: the bound alone; a scalar bound where none is lower,
    the same values as before the cap)."""
    a_min, a_max = sc.bounds.accel_mps2
    lo, hi = constants(a_min, a_max)
    # A vehicle that cannot reach the bound: its own (accel_limit; where none is below the
    # bound it is the bound: count_nonzero here costs a tenth of np.any there, a step).
    if not isinstance(accel, np.ndarray) or np.count_nonzero(np.less(accel, hi)):
        a_max = accel_limit(a_max, accel)
    dt = sc.simulation.step_length_s
    if safety == "sumo":
        gap, decel, lead_decel, lead = layer()
        brake = sc.deploy.command_brake
        # The 0-d bound where it meets the float64 decels only ("bounds" hands the bound on
        # to the actions, which keep Python's weak float).
        a_min = command_brake(a_min if brake == "bounds" else lo, decel, brake)
    cmd = command_speeds(obs[:, 0], act(obs), dt, a_min, a_max, vmax)  # Stage II's rule too
    if cap is not None:
        cmd = np.minimum(cmd, cap)
    if safety != "sumo":
        return cmd
    floor = sc.deploy.safety_floor_share
    if sc.deploy.safety_floor_on == "standing":
        floor = np.where(obs[:, 0] < _STANDING_BELOW, floor, _ZERO)
    floor_safe, tau = None, sc.deploy.safety_floor_reaction_s
    if tau > 0.0:  # a standing vehicle's floor: its safe speed with a reaction time
        v_l = obs[:, 0] - obs[:, 3] if lead_speed is None else lead_speed
        floor_safe = reaction_safe_speed(gap, v_l, decel, lead_decel, dt, tau)
        floor_safe[obs[:, 0] >= _STANDING_BELOW] = _INF
    args = (cmd, obs, gap, decel, lead_decel, lead, dt, a_max, floor, safe, lead_speed, vmax)
    return stats.count_safety(*safety_cap(*args, floor_safe))

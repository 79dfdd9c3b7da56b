"""The deployment's safety layer (``deploy.safety = "sumo"``): what a speed-commanding
driver (``deploy.drivers``) does to a method's commands before SUMO applies them, so that
no command, however poor or adversarial, makes a vehicle collide or block the road.

* Each command is capped at SUMO's Krauss safe speed behind the leader the vehicle
  observes (``road.physics.safe_speed``: the leader's braking at max(b, b_l), as SUMO's),
  the vehicle's own braking b its vType's decel or, with ``deploy.safety_brake =
  "matched"``, at least its moving leader's (``planned_decel``); a vehicle taken over from
  its own model starts from the braking its arrival gap supports, at most its leader's,
  and returns to that b gradually (``BrakeHandover``; these two in ``deploy.brake_plan``,
  re-exported here);
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

from macromicro_sumo.deploy.population import ActionBatch, DriveStats
from macromicro_sumo.road.physics import (
    brake_gap,
    constants,
    count_nonzero,
    safe_speed,
    step_constants,
)
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.road.vtype import accel_limit, command_speeds
from macromicro_sumo.scenario.deploy_settings import DeployConfig

try:  # road/kernels.c, built by setup.py where a C compiler is found (``safety_cap``)
    from macromicro_sumo.road import kernels as _kernels
except ImportError:  # not built: numpy's form, the same values
    _kernels = None
# Each None where not built, or built before it (a checkout's stale build): numpy answers.
_safety_cap = getattr(_kernels, "safety_cap", None)
_leader_safe_speed = getattr(_kernels, "leader_safe_speed", None)

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
# The per-step operands above as read-only 0-d arrays made once (``road.physics.constants``):
# a Python float costs a numpy call a conversion and a weak-scalar promotion, some 0.3 us of
# ~1 us at ~40 rows; on float64 arrays (the deployment's) the values are the same to the bit.
_NO_LEADER_GAP, _INF, _ZERO, _TOLERANCE, _BEHIND_MARGIN, _STANDING_BELOW = constants(
    NO_LEADER_GAP_M, np.inf, 0.0, SAFETY_TOLERANCE_MPS, BEHIND_MARGIN_MPS, STANDING_BELOW_MPS
)
_NO_LEAD = np.zeros((), dtype=np.int64)  # ``lead``'s 0: the first index, -1 is none
_NO_LEAD.flags.writeable = False


def leader_safe_speed(
    obs: np.ndarray,
    gap: np.ndarray,
    decel: np.ndarray,
    lead_decel: np.ndarray,
    dt_s: float,
    lead_speed: np.ndarray | None = None,
    red_gap: np.ndarray | None = None,
) -> np.ndarray:
    """Per vehicle, ``safe_speed`` [m/s] behind the leader it observes (``gap``: SUMO's gap
    to it, ``NO_LEADER_GAP_M`` or more: none, inf; its speed obs[:, 0] - obs[:, 3]; a
    standing leader at a stop line or lane end included): the cap of ``safety_cap``,
    computed once a step and shared with a driver's merge handling (``deploy.drivers``).
    ``lead_speed``: obs[:, 0] - obs[:, 3] if computed already. ``red_gap``: the gap to each
    one's red line (inf: none; None: no light ahead of anyone); a red line beyond a nearer
    leader (one passing its yellow) caps too, as SUMO's driver stops at the line: behind
    the leader alone it sped up to it (drawn 565, stop 44, hC44)."""
    if lead_speed is None:
        lead_speed = obs[:, 0] - obs[:, 3]
    safe = None
    if _leader_safe_speed is not None and type(gap) is np.ndarray:  # no leader's inf too
        safe = np.empty(gap.shape)
        consts = step_constants(dt_s)
        if not _leader_safe_speed(
            gap, lead_speed, decel, lead_decel, *consts, safe, _NO_LEADER_GAP
        ):
            safe = None
    if safe is None:
        safe = safe_speed(gap, lead_speed, decel, lead_decel, dt_s)
        safe[~(gap < _NO_LEADER_GAP)] = _INF  # no leader: no cap (safe_speed's is fresh)
    if red_gap is not None and count_nonzero(behind := (red_gap < _INF) & (gap < red_gap)):
        b = decel[behind]
        line = safe_speed(red_gap[behind], np.zeros_like(b), b, b, dt_s)
        safe[behind] = np.minimum(safe[behind], line)
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
    start: tuple[np.ndarray | float, float, np.ndarray | None] | None = None,
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
    ``reaction_safe_speed``, ``deploy.safety_floor_reaction_s``); ``start``: (the
    vehicles' accel, sigma, the vehicles it applies to or None: all) of
    ``deploy.start_dawdle`` (``start_dawdled``, applied to the capped and floored command
    and, for the counts, to ``cmd``). Returns (commands,
    how many the layer lowered, how many it raised), each by more than
    ``SAFETY_TOLERANCE_MPS``."""
    if lead_speed is None:
        lead_speed = obs[:, 0] - obs[:, 3]
    if safe is None:
        safe = leader_safe_speed(obs, gap, decel, lead_decel, dt_s, lead_speed)
    if _safety_cap is not None and type(cmd) is np.ndarray and cmd.ndim == 1:
        # One compiled pass where built and no driven leader is commanded below what
        # safe_speed assumed (behind_commands' test, most steps): numpy's values and
        # counts to the bit (tests/road/test_kernels_safety.py), its ~25 calls a step
        # between SUMO's steps in one (stop 50). None: numpy's path below answers.
        s = (
            (None, 1.0, None)
            if start is None
            else (start[0], 1.0 - 0.5 * start[1] * dt_s, start[2])
        )
        out = np.empty(cmd.shape[0])
        args = (cmd, obs[:, 0], obs[:, 1], safe, floor_safe, a_max_mps2, dt_s, floor_share, vmax)
        more = (decel, lead_decel, lead, lead_speed, _BEHIND_MARGIN, _TOLERANCE, out)
        if (got := _safety_cap(*args, *s, *more)) is not None:
            return out, got[0], got[1]
    # The road kept open: never below a share of the lane's limit unless what is ahead
    # (the safe speed) asks for it, and no faster than the vehicle may accelerate to it.
    under = safe if floor_safe is None else np.minimum(safe, floor_safe)
    floor = np.minimum(under, np.minimum(obs[:, 0] + a_max_mps2 * dt_s, floor_share * obs[:, 1]))
    floor = np.minimum(floor, vmax)
    capped = np.minimum(cmd, safe)
    raised = int(count_nonzero(floor > capped + _TOLERANCE))
    out = np.maximum(capped, floor)
    if start is not None:  # before behind_commands: a driven follower sees the dawdled one
        least = obs[:, 0] - decel * dt_s  # never braking beyond the decel, as SUMO's
        out = start_dawdled(out, start[0], start[1], dt_s, least, start[2])
        cmd = start_dawdled(cmd, start[0], start[1], dt_s, least, start[2])
    out = behind_commands(out, gap, lead, decel, lead_decel, dt_s, lead_speed)
    return out, int(count_nonzero(out < cmd - _TOLERANCE)), raised


def start_dawdled(
    cmd: np.ndarray,
    accel: np.ndarray | float,
    sigma: float,
    dt_s: float,
    least: np.ndarray | float = 0.0,
    on: np.ndarray | None = None,
) -> np.ndarray:
    """``deploy.start_dawdle`` = ``sigma``: each speed command [m/s] below the vehicle's
    ``accel`` [m/s^2, as a number] lowered by SUMO's Krauss dawdle of a starting driver,
    at its mean: v' (1 - sigma dt / 2), but not below ``least`` (v - b dt: the speed its
    decel brakes to in the step) unless the command was. ``MSCFModel_Krauss::dawdle2``
    takes sigma v' U dt off a next speed v' below a (U uniform in [0, 1)), after the safe
    speed's cap, and ``finalizeSpeed`` keeps it at least v - b dt: the step a standing car
    starts in, and every creeping one, not only the acceleration (without that bound a car
    braking at its decel to below a braked beyond it: 1164, 1,084 emergency brakings).
    ``dawdled_accel`` (``deploy.command_dawdle``) takes its mean off the acceleration
    bound from the current speed v, nothing at v = 0, and never off a command the safe
    speed capped: a standing queue's car went at room / dt the step after its leader
    moved (1164: start lags 0.52-0.58 s a car, the truth's 0.84-0.95). Lowering a command
    is safe; the driven followers are capped behind it (``behind_commands``). ``on``: the
    vehicles it applies to (``deploy.start_rules``; None: all)."""
    low = cmd < accel
    if on is not None:
        low &= on
    if not count_nonzero(low):
        return cmd
    dawdled = np.maximum(cmd * (1.0 - 0.5 * sigma * dt_s), np.minimum(cmd, least))
    return np.where(low, dawdled, cmd)


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
        if not count_nonzero(led & (cmd[lead] < least)):
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
        if not count_nonzero(lower):
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


def dawdled_accel(accel: np.ndarray | float, speed: np.ndarray, sigma: float) -> np.ndarray | float:
    """The most acceleration [m/s^2] a command may ask with ``deploy.command_dawdle`` =
    ``sigma`` > 0: a - sigma / 2 min(v, a) (a: ``accel``, the bound at most the vType's
    accel, per vehicle or one; v: ``speed``), the mean acceleration of SUMO's Krauss driver
    of imperfection sigma: its dawdling takes sigma U min(v, a) off it, U uniform in [0, 1)
    (``MSCFModel_Krauss::dawdle2``: v below a loses sigma v U dt a step, faster a car loses
    sigma a U dt), so 1.95 m/s^2 at a = 2.6, sigma = 0.5 (SUMO's defaults) from 2.6 m/s on.

    Why: the policy's mean action has no dawdling, and where the fit could not identify a
    (too few free-acceleration pairs) its Krauss prior falls back to the vType's 2.6. Drawn
    arterial 528, all 4 runs: the policy's cars accelerated freely at 2.26-2.47 m/s^2
    between 1 and 8 m/s, the truth's at 1.86-2.01 (docs/deploy-log.md, the discharge at
    signals, stop 45)."""
    return accel - (0.5 * sigma) * np.minimum(speed, accel)


# SUMO's Krauss imperfection by default: the sigma "auto" dawdles with (hD46, stop 46: each
# vType's own sigma measured worse).
AUTO_SIGMA = 0.5


def command_dawdle_sigma(setting: str | float, lights: bool) -> str | float:
    """``deploy.command_dawdle`` on a network with or without traffic lights: "auto" where
    the prior-gated rule acts (``auto_dawdled_accel``: "auto", or "signals" with lights),
    else the sigma the commands dawdle at (0: none). The deployment's rule, and the one
    ``policy.relax_refit = "dawdled"`` fits the relaxation to (``pipeline.build``)."""
    if setting == "auto" or (setting == "signals" and lights):
        return "auto"
    return 0.0 if isinstance(setting, str) else float(setting)


def auto_dawdled_accel(
    accel: np.ndarray | float, speed: np.ndarray, prior_accel: float | None
) -> np.ndarray | float:
    """``deploy.command_dawdle = "auto"``: ``dawdled_accel`` at sigma ``AUTO_SIGMA`` on the
    vehicles whose bound ``accel`` (at most the vType's a) has a dawdled mean a (1 - sigma /
    2) below the policy's Krauss prior's a ``prior_accel`` [m/s^2]; ``accel`` unchanged
    elsewhere, and everywhere without a Krauss prior (None).

    Why: dawdle only where the prior does not already. A prior's a that fell back to the
    vType's 2.6 (too few free pairs, or most pairs faster than the fit: every drawn net and
    netgen_corridor) never saw a dawdled mean: 0.5 there won on the signalised arterials
    (528 1.131 -> 1.001, 521 0.995 -> 0.911 m/s). A fitted a (Bremen's 1.80, below 1.95)
    carries the dawdle already: 0.5 there lost 0.914 -> 1.035, all from the floor's cap
    (docs/deploy-log.md, stop 46). A prior other than krauss (none, idm, gipps) has no a of
    the Krauss mean's form: off. On the drawn motorways "auto" lost (1045 2.921 -> 4.212
    m/s): "signals" keeps it to networks with traffic lights."""
    if prior_accel is None:
        return accel
    on = np.greater(prior_accel, accel * (1.0 - 0.5 * AUTO_SIGMA))
    n = count_nonzero(on)  # a tenth of np.any's cost on a small array, a step
    if not n:
        return accel  # off: the same values, so the same commands to the bit
    dawdled = dawdled_accel(accel, speed, AUTO_SIGMA)
    if n == np.size(on):
        return dawdled  # on everywhere: the same as command_dawdle = 0.5 to the bit
    return np.where(on, dawdled, accel)


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
    lights: bool = False,
    start_on: np.ndarray | None = None,
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
    the same values as before the cap); with ``deploy.command_dawdle`` both are at most
    ``dawdled_accel``'s (``auto_dawdled_accel``'s with "auto", and with "signals" where
    ``lights``: the network has traffic lights). ``start_on``: the vehicles the start rules
    (``deploy.start_dawdle``, ``deploy.start_reaction_s``) apply to, by
    ``deploy.start_rules`` (None: all where it is "all", none where it is "signal_lanes":
    a caller that does not name them, which knows no lanes, gets the commands without the
    rules; none named: those commands, to the bit)."""
    a_min, a_max = sc.bounds.accel_mps2
    lo, hi = constants(a_min, a_max)
    # A vehicle that cannot reach the bound: its own (accel_limit; where none is below the
    # bound it is the bound: count_nonzero here costs a tenth of np.any there, a step).
    if not isinstance(accel, np.ndarray) or count_nonzero(np.less(accel, hi)):
        a_max = accel_limit(a_max, accel)
    start_sigma, start_tau = sc.deploy.start_dawdle, sc.deploy.start_reaction_s
    if start_on is None and sc.deploy.start_rules != "all":
        start_sigma = start_tau = 0.0  # gated, and nobody named
    elif start_on is not None and not count_nonzero(start_on):
        start_sigma = start_tau = 0.0  # nobody's: the path without the rules
    start = (a_max, start_sigma, start_on) if start_sigma > 0.0 else None  # SUMO's a
    sigma = command_dawdle_sigma(sc.deploy.command_dawdle, lights)
    if sigma == "auto":
        a_max = auto_dawdled_accel(a_max, obs[:, 0], getattr(act, "prior_accel_mps2", None))
    elif sigma > 0.0:
        a_max = dawdled_accel(a_max, obs[:, 0], sigma)
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
    if start_tau > 0.0:
        # A standing vehicle's command and floor at most SUMO's Krauss safe speed with the
        # drivers' tau, as its own drivers start (deploy.start_reaction_s): computed for
        # the standing ones alone (elementwise IEEE operations: the same values as over all).
        standing = obs[:, 0] < _STANDING_BELOW
        if start_on is not None:
            standing &= start_on
        idx = standing.nonzero()[0]
        if idx.size:  # none: the floor's and the cap's values as with every one at inf
            v_l = obs[:, 0] - obs[:, 3] if lead_speed is None else lead_speed
            start_safe = np.full(len(cmd), _INF)
            start_safe[idx] = reaction_safe_speed(
                gap[idx], v_l[idx], _at(decel, idx), _at(lead_decel, idx), dt, start_tau
            )
            cmd = np.minimum(cmd, start_safe)
            floor_safe = start_safe if floor_safe is None else np.minimum(floor_safe, start_safe)
    args = (cmd, obs, gap, decel, lead_decel, lead, dt, a_max, floor, safe, lead_speed, vmax)
    return stats.count_safety(*safety_cap(*args, floor_safe, start))


def _at(x: np.ndarray | float, idx: np.ndarray) -> np.ndarray | float:
    """``x`` at ``idx`` where it is per vehicle, else the one value for all."""
    return x[idx] if np.ndim(x) else x

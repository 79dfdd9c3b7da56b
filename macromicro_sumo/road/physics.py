"""Pure, vectorised car-following physics: the IDM, the observation features and the
Krauss/Gipps safe speed.

Nothing here knows SUMO; every function takes and returns numpy arrays in SI units.
"""

from __future__ import annotations

import numpy as np

try:  # numpy 2: the compiled function that np.count_nonzero wraps
    from numpy._core.multiarray import count_nonzero
except ImportError:  # numpy 1.x: the wrapper (the same counts)
    count_nonzero = np.count_nonzero
# ``count_nonzero``: the number of nonzero (True) values of an array, as np.count_nonzero(a)
# with no axis gives it, without its Python wrapper and array-function dispatch: 0.16-0.20
# against 0.55-0.68 us a call at 42 values (numpy 2.4, measured, stop 46). The hot paths of
# a deployment's step ask it a dozen times ("is anyone ...?"), each one between SUMO's steps.
try:  # road/kernels.c, built by setup.py where a C compiler is found (``safe_speed``)
    from macromicro_sumo.road import kernels as _kernels
except ImportError:  # not built: numpy's form, the same values
    _kernels = None


def idm_accel(
    speed_mps: np.ndarray,
    gap_m: np.ndarray,
    delta_v_mps: np.ndarray,
    desired_speed_mps: np.ndarray,
    tau_s: np.ndarray,
    accel_mps2: np.ndarray,
    decel_mps2: np.ndarray,
    min_gap_m: np.ndarray,
    delta: float | np.ndarray = 4.0,
) -> np.ndarray:
    """Textbook IDM acceleration [m/s^2] (Treiber et al. 2000).

    ``gap_m`` is the bumper-to-bumper gap, ``delta_v_mps = v_ego - v_leader`` (positive
    when closing in). The dynamic term of the desired gap is floored at zero, as SUMO does.
    """
    s_star = min_gap_m + np.maximum(
        0.0, speed_mps * tau_s + speed_mps * delta_v_mps / (2.0 * np.sqrt(accel_mps2 * decel_mps2))
    )
    free = 1.0 - (speed_mps / desired_speed_mps) ** delta
    return accel_mps2 * (free - (s_star / np.maximum(gap_m, 1e-9)) ** 2)


SCENE_FEATURES = {
    "paper": ("speed_mps", "speed_limit_mps", "spacing_m", "delta_v_mps"),
    "lookahead": (
        "speed_mps",
        "speed_limit_mps",
        "spacing_m",
        "delta_v_mps",
        "next_limit_mps",
        "dist_to_next_m",
    ),
    # The leader column is the bumper-to-bumper gap (the leader's rear minus the own front,
    # with the leader's own length), not the front-to-front spacing: behind a 12 m truck a
    # 13 m spacing is a 1 m gap, which "lookahead" showed the policy as a car's 8 m one (on
    # drawn 501, 17 of 57 Stage II episodes with the safety layer off ran a hidden car into
    # an observed truck; docs/deploy-log.md, "Drawn 501 at stop 35").
    "lookahead_gap": (
        "speed_mps",
        "speed_limit_mps",
        "gap_m",
        "delta_v_mps",
        "next_limit_mps",
        "dist_to_next_m",
    ),
}
# Features of the vehicle itself, not of the scene around it: after the scene's, in this
# order, each set from an attribute every observer knows (``set_own_features``). The own
# length is what the generator draws, the recorded trajectories' vType gives and SUMO
# reports of a deployed vehicle: one policy could drive a mixed fleet's trucks and cars
# each as they drive. Measured on drawn nets 300 and 311 it did not (the trucks' time gap
# moved away from the truth's), so it is an option, not the default (docs/deploy-log.md, "A
# policy that knows its vehicle's length (stop 31)").
OWN_FEATURES = ("length_m",)
OBSERVATION_FEATURES = {
    **SCENE_FEATURES,
    "lookahead_length": SCENE_FEATURES["lookahead"] + OWN_FEATURES,
    "lookahead_gap_length": SCENE_FEATURES["lookahead_gap"] + OWN_FEATURES,
}
# Columns of the own lane's limit, the leader (spacing or gap) and the next edge's limit
# (the look-ahead layouts; "paper" has no next edge).
LIMIT_COLUMN, LEADER_COLUMN, NEXT_LIMIT_COLUMN = 1, 2, 4


def has_lookahead(observation: str) -> bool:
    """Whether ``policy.observation`` carries the next edge's limit and distance."""
    return "next_limit_mps" in OBSERVATION_FEATURES[observation]


def observes_length(observation: str) -> bool:
    """Whether ``policy.observation`` carries the vehicle's own length."""
    return "length_m" in OBSERVATION_FEATURES[observation]


def observes_gap(observation: str) -> bool:
    """Whether ``policy.observation``'s leader column is the bumper-to-bumper gap
    (``gap_m``), not the front-to-front spacing (``spacing_m``)."""
    return "gap_m" in OBSERVATION_FEATURES[observation]


def leader_length_m(observation: str, length_m: float) -> float:
    """The length a car-following model subtracts from ``policy.observation``'s leader
    column to get the bumper gap: ``length_m`` (the leader taken as long as the vehicle, all
    a spacing tells) where it is the spacing, 0 where it is the gap already (the leader's
    true length in it)."""
    return 0.0 if observes_gap(observation) else float(length_m)


def set_own_features(obs: np.ndarray, observation: str, length_m: np.ndarray | None) -> np.ndarray:
    """Fill ``obs``' (..., F) own-vehicle columns (``OWN_FEATURES``) of ``policy.observation``
    in place from each vehicle's ``length_m`` (...,); returns ``obs``. The one definition
    that the training envs, the micro pairs and the deployment share. Scene-only
    observations are left as they are (``length_m`` may then be None)."""
    if observes_length(observation):
        if length_m is None:
            raise ValueError(f"policy.observation = {observation!r} needs each vehicle's length")
        obs[..., OBSERVATION_FEATURES[observation].index("length_m")] = length_m
    return obs


def no_lower_limit_ahead(obs):
    """(...,) bool of (..., F) observations, numpy or torch: the next edge's limit is not
    below the own one (all True where the observation has no look-ahead). Why: SUMO's
    drivers start braking for a lower limit ahead long before they reach it, which IDM's
    [v, v_limit, spacing, delta_v] cannot see. Fitted to every pair of the paper's ring, IDM
    took those for drivers that barely accelerate (a = 0.18 m/s^2, the fleet's 0.8-1.2): in
    the leader-follower tests it fell 0.78 / 0.55 m/s behind the fleet's IDM; on these pairs
    (60%) a = 0.53, 0.22 / 0.20 m/s (docs/design.md, "Leader-follower across PPO seeds")."""
    if obs.shape[-1] <= NEXT_LIMIT_COLUMN:  # every pair (``| True``: NaN limits too)
        return (obs[..., LIMIT_COLUMN] == obs[..., LIMIT_COLUMN]) | True
    return obs[..., NEXT_LIMIT_COLUMN] >= obs[..., LIMIT_COLUMN]


def constant(value: float) -> np.ndarray:
    """``value`` as a read-only 0-d float64 array."""
    out = np.array(float(value))
    out.flags.writeable = False
    return out


# ``brake_gap``'s and ``safe_speed``'s constants as 0-d float64 arrays, made once: in numpy
# 2.4 a Python float operand costs each call a conversion and a weak-scalar promotion, some
# 0.3-0.5 us of a 0.7-1.2 us call at ~40 rows (docs/deploy-log.md, hB44 at stop 44); on
# float64 inputs the values are the same to the bit. A 0-d array is a strong type, though:
# float32 inputs now give float64 results (every caller passes float64).
_ZERO, _ONE, _MINUS_ONE, _TWO, _EIGHT = map(constant, (0.0, 1.0, -1.0, 2.0, 8.0))
# Per step length dt [s] met: (dt, dt * dt) as 0-d arrays (``step_constants``).
_STEP_CONSTANTS: dict[float, tuple[np.ndarray, np.ndarray]] = {}


def step_constants(dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(dt, dt**2) of the step length ``dt_s`` [s] as read-only 0-d arrays, kept per dt (a
    run has one; at most 16 kept, so that a caller sweeping dt cannot grow the cache)."""
    dt = float(dt_s)
    try:
        return _STEP_CONSTANTS[dt]
    except KeyError:
        got = (constant(dt), constant(dt**2))
        if len(_STEP_CONSTANTS) < 16:
            _STEP_CONSTANTS[dt] = got
        return got


# Per tuple of values met: the values as 0-d arrays (``constants``).
_CONSTANTS: dict[tuple[float, ...], tuple[np.ndarray, ...]] = {}


def constants(*values: float) -> tuple[np.ndarray, ...]:
    """``values`` as read-only 0-d float64 arrays (``constant``), kept per tuple of values:
    a run's per-step operands (its bounds, ...) made once (at most 64 tuples kept)."""
    try:
        return _CONSTANTS[values]
    except KeyError:
        got = tuple(map(constant, values))
        if len(_CONSTANTS) < 64:
            _CONSTANTS[values] = got
        return got


def brake_gap(speed_mps: np.ndarray, decel_mps2: np.ndarray | float, dt_s: float) -> np.ndarray:
    """Distance [m] a vehicle covers braking at ``decel_mps2`` from ``speed_mps`` in Euler
    steps of ``dt_s`` (v' = max(0, v - b dt), x' = x + v' dt): SUMO's ``brakeGap``
    (headway 0). At most the continuous v^2 / 2b; short by up to v dt / 2 when b dt is large
    next to v, the braking that a few coarse steps stop."""
    dt = step_constants(dt_s)[0]
    reduction = np.multiply(decel_mps2, dt)
    steps = np.floor(np.asarray(speed_mps) / reduction)
    return dt * (steps * speed_mps - reduction * steps * (steps + _ONE) / _TWO)


def safe_speed(
    gap_m: np.ndarray,
    leader_speed_mps: np.ndarray,
    decel_mps2: np.ndarray | float,
    leader_decel_mps2: np.ndarray | float,
    dt_s: float,
) -> np.ndarray:
    """SUMO's Krauss safe speed (Gipps) [m/s] in Euler steps: the fastest speed v from which
    the vehicle, moving one step at v and braking at its decel b after it, stops behind a
    leader that brakes from now on at its decel b_l or at b, whichever is harder:
    v dt + brake_gap(v, b) <= gap + brake_gap(v_l, max(b, b_l)) (SUMO's
    ``maximumSafeFollowSpeed`` with ``maximumSafeStopSpeedEuler``, reaction time one step).

    The leader's distance is taken at max(b, b_l) as SUMO does: with b_l alone, a follower
    that brakes harder than its leader (b > b_l) may drive faster than the leader at no gap
    (its shorter stop still ends behind the leader's), and the two trajectories cross
    before either stops: on the ring a follower with b = 1.43 closed in at 0.25 m/s on a
    leader with b_l = 1.22 from its minGap to -3.5 m, uncapped (tested).

    The continuous form v dt + v^2 / 2b <= gap + v_l^2 / 2b_l (deploy's first definition)
    overstates the leader's braking distance by up to v_l dt / 2 where it brakes hard in
    coarse steps (followers ran into it; tested); the leader's Euler distance beside the
    follower's continuous one would understate the room by as much and cap a follower one
    step behind a leader of its speed and decel, where both forms agree on v = v_l.
    The condition is on where both stop; with the leader braking at least as hard as the
    follower it holds on the way too (a follower faster than its leader stays faster until
    it stops, so the gap only shrinks). ``gap_m`` is the bumper-to-bumper gap; a negative
    one counts as 0. Never negative.
    """
    dt, dt2 = step_constants(dt_s)
    # The compiled pass where built and the operands are float64 vectors or scalars: the
    # same values to the bit (tests/road/test_kernels.py), one call for numpy's ~28.
    if _kernels is not None and type(gap_m) is np.ndarray:
        out = np.empty(gap_m.shape)
        if _kernels.safe_speed(
            gap_m, leader_speed_mps, decel_mps2, leader_decel_mps2, dt, dt2, out
        ):
            return out
    lead_b = np.maximum(decel_mps2, leader_decel_mps2)
    room = np.maximum(gap_m, _ZERO) + brake_gap(leader_speed_mps, lead_b, dt_s)
    # v dt + brake_gap(v, b) is piecewise linear in v, (n + 1) v dt - b dt^2 n (n + 1) / 2
    # with n = floor(v / b dt), and b dt^2 n (n + 1) / 2 at v = n b dt: invert it piece-wise.
    bdt2 = np.multiply(decel_mps2, dt2)
    n = np.floor((_MINUS_ONE + np.sqrt(_ONE + _EIGHT * room / bdt2)) / _TWO)
    n1 = n + _ONE  # the same value both times: computed once
    return (room + bdt2 * n * n1 / _TWO) / (dt * n1)

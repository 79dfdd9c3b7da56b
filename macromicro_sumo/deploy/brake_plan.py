"""The braking the deployment's safety layer (``deploy.safety``) plans each driven vehicle's
stop with: its vType's decel, or with ``deploy.safety_brake = "matched"`` at least its moving
leader's (``planned_decel``); a vehicle taken over from its own model starts from the braking
its arrival gap supports (``supported_decel``) and returns to that gradually
(``BrakeHandover``). Split from ``deploy.safety`` (stop 45); import these names from here.

Pure numpy: tested without SUMO and, through the drivers, with it
(``tests/deploy/test_safety_brake.py``, ``tests/deploy/test_safety_handover.py``).
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.deploy.observe import STOP_DECEL_MPS2
from macromicro_sumo.road.physics import brake_gap, count_nonzero, safe_speed
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.scenario.deploy_settings import DeployConfig

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
    if not count_nonzero(short):
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
    if not count_nonzero(short):
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
        if count_nonzero(fresh):
            new = on[fresh]
            self._end[slots[new]] = -np.inf
            # supported_decel's, its state read only where a leader may ask more (no new
            # driver's on Bremen: there each step with one costs a few numpy calls).
            lo, ahead, lead_b = decel[new], gap[new], lead_decel[new]
            short = _beyond_own(ahead, lo, lead_b)
            got = ramp = None
            if count_nonzero(short):
                got = _supported(short, ahead, lead_speed[new], speed[new], lo, lead_b, self.dt_s)
                ramp = got > lo
            if ramp is not None and count_nonzero(ramp):
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

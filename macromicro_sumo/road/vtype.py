"""A commanded vehicle's own physics: its vType's maxSpeed and accel, and the one speed
command rule that holds a command to them.

SUMO applies a speed command exactly under the speed modes the deployment and Stage II use
(the max-accel bit off), so neither bound holds unless the command is held to it, while
SUMO's Krauss and IDM never exceed either: drawn net 300's trucks (accel 1.0) accelerated
at the policy's bound of 2.6 m/s^2 until the deployment capped them. ``command_speeds`` is
the rule both the deployment's drivers (``deploy.safety.speed_commands``) and Stage II's
envs (``env.slot_core``, ``env.demand``) apply, so that a policy trains under the physics it
is deployed with.

Pure numpy, but for ``read_vtype``, which reads one vType's record from SUMO.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macromicro_sumo.road.leaders import STOPLINE_GAP_M
from macromicro_sumo.sumo.simulation import Simulation

try:  # road/kernels.c, built by setup.py where a C compiler is found (``command_speeds``)
    from macromicro_sumo.road import kernels as _kernels
except ImportError:  # not built: numpy's form, the same values
    _kernels = None
_command_speeds = getattr(_kernels, "command_speeds", None)  # None: built before it too


@dataclass(frozen=True)
class VTypePhysics:
    """One vType as SUMO has it (``read_vtype``): read once per vType, held in one place."""

    length_m: float
    min_gap_m: float
    decel_mps2: float  # its model's braking, what safe speeds plan a stop with
    max_speed_mps: float  # the vehicle's cap: no command takes it faster
    accel_mps2: float  # its model's acceleration: no command accelerates it harder
    # jmStoplineGap: where its driver stops before a red line (``road.leaders.
    # stop_distance_m``); SUMO's default where the vType sets none.
    stopline_gap_m: float = STOPLINE_GAP_M

    @property
    def shape(self) -> tuple[float, float, float]:
        """(length [m], minGap [m], decel [m/s^2]): what an observation of it needs."""
        return self.length_m, self.min_gap_m, self.decel_mps2


def read_vtype(sim: Simulation, type_id: str) -> VTypePhysics:
    """vType ``type_id``'s record from the running simulation ``sim`` (SUMO's values, its
    vClass's defaults where the user's files set none)."""
    gap = sim.vtype_stopline_gap(type_id)
    return VTypePhysics(
        *sim.vtype_shape(type_id),
        sim.vtype_max_speed(type_id),
        sim.vtype_accel(type_id),
        STOPLINE_GAP_M if gap is None else gap,
    )


def accel_limit(bound_mps2: float, accel_mps2: np.ndarray | float) -> np.ndarray | float:
    """The largest acceleration [m/s^2] a command may ask of each vehicle: the policy's
    upper bound ``bound_mps2``, at most the vehicle's vType accel ``accel_mps2`` (per vehicle,
    or one; inf: unknown). The bound itself, a scalar, where no vehicle's accel is below it:
    the commands are then those of the bound alone, to the bit (a float32 action clipped at
    a float64 array would not be)."""
    if np.any(np.less(accel_mps2, bound_mps2)):
        return np.minimum(accel_mps2, bound_mps2)
    return bound_mps2


def command_speeds(
    speed_mps: np.ndarray,
    accel_mps2: np.ndarray,
    dt_s: float,
    a_min_mps2: float,
    a_max_mps2: np.ndarray | float,
    vmax_mps: np.ndarray | float = np.inf,
) -> np.ndarray:
    """Speed commands v' = max(0, v + a dt) [m/s] of vehicles at speeds ``speed_mps`` asked
    for accelerations ``accel_mps2``: a clipped to [``a_min_mps2``, ``a_max_mps2``] (per
    vehicle: ``accel_limit``), v' at most each vehicle's maxSpeed ``vmax_mps``."""
    # The compiled pass where built and the operands are float64 (the deployment's): the
    # same values to the bit (tests/road/test_kernels_safety.py), one call for numpy's
    # six, each step between SUMO's (stop 50).
    if _command_speeds is not None and type(accel_mps2) is np.ndarray and accel_mps2.ndim == 1:
        out = np.empty(accel_mps2.shape[0])
        if _command_speeds(speed_mps, accel_mps2, dt_s, a_min_mps2, a_max_mps2, vmax_mps, out):
            return out
    # np.clip's own overhead is several times that of the two calls (the same values).
    a = np.minimum(np.maximum(accel_mps2, a_min_mps2), a_max_mps2)
    return np.minimum(np.maximum(0.0, speed_mps + a * dt_s), vmax_mps)

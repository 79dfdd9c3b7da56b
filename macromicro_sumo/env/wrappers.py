"""Public environments: gymnasium (one hidden vehicle) and PettingZoo (K hidden vehicles,
one shared policy) over a section of a network, the paper's ring among them
(``SectionHiddenEnv``, ``SectionHiddenParallelEnv`` in ``env/section_envs.py``: wrap
``env.SectionCore``). Registered with gymnasium as ``macromicro/SectionHidden-v0`` and, the
same env, ``macromicro/RingHidden-v0`` when this module is imported; this module holds what
the envs share and registers them.

## Action Space
Per hidden vehicle: ``Box(a_min, a_max, (1,), float32)``, the longitudinal acceleration
[m/s^2] (``bounds.accel_mps2``, the paper's [-1.1, 0.5]). It is clipped to the bounds and
applied as a speed command v' = max(0, v + a dt) in SUMO speed mode 0. With
``normalize=True``: ``Box(-1, 1, (1,), float32)``, mapped linearly onto [a_min, a_max]
(-1 -> a_min, 1 -> a_max; on the paper's ring 0 is -0.3 m/s^2). A wrong shape or a
NaN/inf raises ``ValueError`` naming the agent.

## Observation Space
Per hidden vehicle: ``Box(4,)`` = [v (m/s), v_limit at its position (m/s), spacing to the
vehicle ahead, front to front (m), v - v_leader (m/s)], from arc positions (the paper's
observation). With ``policy.observation = "lookahead"``: ``Box(6,)``, adding the next
edge's speed limit (m/s) and the distance to it (m); ``"lookahead_gap"`` has the
bumper-to-bumper gap to the leader (its own length) in place of the spacing. With ``normalize=True`` each feature
is (value - shift) / scale with the mean and std of the bank's initial observations (the
PPO agent's), and the bounds move with it.

## Rewards
r_macro,t = 1 / (1 + lambda_v L_speed,t + lambda_d L_dist,t) on the whole scene
(``macromicro_sumo.data.objective``), the same for every hidden vehicle (the trainer weights
it by eta). The micro term is not a reward:
``info["observed_obs"]`` (M, 4) and ``info["observed_action_mps2"]`` (M,) carry each observed
vehicle's observation in the simulated scene and its recorded action at this step, for the
likelihood term. ``info`` also has ``collision``, ``error`` (a SUMO failure, if any), the
named terms of ``data.objective``.

## Starting State
A snapshot of a ground-truth run (the ``split``'s runs) with K hidden vehicles, completed
by the trained generator and placed in SUMO (moved, not re-inserted: SUMO is not restarted).
Observed vehicles replay their recorded speeds.

## Episode End
Truncated after H = ``policy.horizon`` steps of ``simulation.step_length_s`` seconds (10 x
0.5 s on the paper's ring); terminated on a collision (bumper gap below 0); truncated early
with ``info["error"]`` if SUMO fails. ``gymnasium.make`` wraps the env in a ``TimeLimit`` of
H steps, so ``env.spec.max_episode_steps`` is the scenario's H.

## Arguments
``scenario`` (TOML path), ``data`` (ground-truth folder), ``generator`` (generator.pt, or
``None`` to start from the true hidden states), ``split`` ("train", "val", "held_out"),
``hidden`` (K, or a (low, high) range; gymnasium: 1), ``seed``, ``normalize`` (False:
SI units; True: actions in [-1, 1] and normalised observations, for off-the-shelf RL
libraries such as Stable-Baselines3), ``render_mode`` (None only). With no ``scenario``,
``data`` and ``generator`` the envs run the demo: the shipped ``ring_paper`` scenario with
20 runs, whose ground truth and generator are built once (seeded) into a per-user cache
folder (``env.examples``; said on stderr), so that ``gymnasium.make("macromicro/RingHidden-v0")``
works as is.

## Sections
The scenario is a section of a network (a ring file is its closed one-lane section), the ground
truth ``macromicro simulate``'s, the generator ``train-generator``'s (``None``: the true
hidden vehicles). Each episode has its own hidden count K (``generator.k_source``);
episodes without a hidden vehicle are left out. Vehicles change lanes (SUMO's model) and
leave an open section. Observations as ``env.SectionCore``'s (spacing ``NO_LEADER_GAP_M``
= 250 m and delta_v 0 with no leader ahead on the lane; zeros once off the section); with
``normalize=True`` the shift and scale are the mean and std of the bank's initial
observations, the PPO agent's. PettingZoo: agents
``hidden_0 .. hidden_{K-1}``; an agent whose vehicle leaves the section is terminated and
drops out. Gymnasium: the agent drives one hidden vehicle drawn at each reset; the others
apply ``others`` (a constant acceleration [m/s^2], default 0, or a function of their raw
observations (K-1, d) returning K-1 accelerations); the episode terminates when its vehicle
leaves the section or on a collision.

## One SUMO simulation per process
libsumo runs one simulation per process. A second env (or ``gymnasium.utils.env_checker.
check_env``'s, which builds and closes one) takes it over; the first env's ``reset()``
then starts its own run again (a fresh SUMO run of the same network), while its ``step()``
without that reset raises ``UserError``. Vectorise with subprocesses:
``gymnasium.vector.AsyncVectorEnv`` (``gymnasium.make_vec(..., vectorization_mode="async")``)
or Stable-Baselines3's ``SubprocVecEnv``; a ``SyncVectorEnv`` or ``DummyVecEnv`` of more
than one env is refused when it is built.
"""

from __future__ import annotations

import sys
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from macromicro_sumo.env.observation import shift_scale
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.physics import OBSERVATION_FEATURES

ENV_ID = "macromicro/RingHidden-v0"
SECTION_ENV_ID = "macromicro/SectionHidden-v0"


# Bounds of the raw observation features; "length" is the road's length [m].
_FEATURE_BOUNDS = {
    "speed_mps": (0.0, 100.0),
    "speed_limit_mps": (0.0, 100.0),
    "spacing_m": (0.0, "length"),
    "delta_v_mps": (-100.0, 100.0),
    "next_limit_mps": (0.0, 100.0),
    "dist_to_next_m": (0.0, "length"),
}


class Scaling:
    """The agent's units <-> the core's: actions (m/s^2) and observations (SI), raw or
    normalised (``normalize``; the module docstring's Action and Observation Space)."""

    def __init__(
        self,
        accel_mps2: tuple[float, float],
        observation: str,
        length_m: float,
        normalize: bool,
        shift_scale_: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        self.a_min, self.a_max = (float(a) for a in accel_mps2)
        self.normalize = bool(normalize)
        names = OBSERVATION_FEATURES[observation]
        lo = np.array([_FEATURE_BOUNDS[n][0] for n in names], dtype=np.float64)
        hi = np.array(
            [
                length_m if _FEATURE_BOUNDS[n][1] == "length" else _FEATURE_BOUNDS[n][1]
                for n in names
            ]
        )
        if self.normalize:
            self.shift, self.scale = shift_scale_ or shift_scale(observation)
            lo, hi = (lo - self.shift) / self.scale, (hi - self.shift) / self.scale
            self.action_space = spaces.Box(np.float32(-1), np.float32(1), (1,), np.float32)
        else:
            self.shift, self.scale = np.zeros(len(names)), np.ones(len(names))
            self.action_space = spaces.Box(
                np.float32(self.a_min), np.float32(self.a_max), (1,), np.float32
            )
        self.observation_space = spaces.Box(
            lo.astype(np.float32), hi.astype(np.float32), dtype=np.float32
        )

    def accel(self, action: float) -> float:
        """The acceleration [m/s^2] an action asks for (the core clips it to the bounds)."""
        if not self.normalize:
            return action
        return self.a_min + (action + 1.0) * 0.5 * (self.a_max - self.a_min)

    def obs(self, raw: np.ndarray) -> np.ndarray:
        """Observations (..., d) in the agent's units, float32."""
        if not self.normalize:
            return raw.astype(np.float32)
        return ((raw - self.shift) / self.scale).astype(np.float32)


# Vector envs that step their envs one after the other in this process: (module, class).
_IN_PROCESS_VECTORS = {
    ("gymnasium.vector.sync_vector_env", "SyncVectorEnv"): "gymnasium.vector.SyncVectorEnv",
    ("stable_baselines3.common.vec_env.dummy_vec_env", "DummyVecEnv"): "DummyVecEnv",
}
_SUBPROCESS_HINT = (
    "gymnasium.vector.AsyncVectorEnv (gymnasium.make_vec(..., vectorization_mode='async')) "
    "or stable_baselines3's SubprocVecEnv"
)


def refuse_in_process_vector(name: str) -> None:
    """Fail while a vector env that would hold several of these envs in this process is
    being built: libsumo runs one simulation per process, so each env's reset would take
    SUMO from the others and their steps would fail."""
    frame = sys._getframe(1)
    while frame is not None:
        owner = frame.f_locals.get("self") if frame.f_code.co_name == "__init__" else None
        cls = type(owner)
        vector = _IN_PROCESS_VECTORS.get((cls.__module__, cls.__name__))
        if vector is not None:
            try:
                n = len(frame.f_locals.get("env_fns", ()))
            except TypeError:  # an iterator of env functions: its length is unknown
                n = 1
            if n > 1:
                raise UserError(
                    f"{vector} would run {n} {name} envs in one process, but libsumo runs one "
                    f"SUMO simulation per process; use {_SUBPROCESS_HINT}: one process per env"
                )
        frame = frame.f_back


def check_render_mode(render_mode: str | None) -> None:
    """Refuse a render mode: the envs render nothing."""
    if render_mode is not None:
        raise ValueError(f"render_mode {render_mode!r} is not supported; accepted: None")


def check_action(agent: str, action: Any) -> float:
    """An agent's action as a float; ``ValueError`` naming the agent for a wrong shape or a
    NaN/inf."""
    a = np.asarray(action, dtype=np.float64)
    if a.shape not in ((1,), ()):
        raise ValueError(f"agent {agent}: action must have shape (1,), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"agent {agent}: action must be finite, got {a.reshape(-1)[0]}")
    return float(a.reshape(-1)[0])


def step_info(core: SectionCore, res=None) -> dict[str, Any]:
    """The observed vehicles on the road now, their observations and recorded actions (NaN
    where unknown), and the step's outcome and named reward terms."""
    obs = core.observations()
    observed = core.active & ~core.hidden
    t = min(core.t, core.bank.gt_accel_mps2.shape[1] - 1)
    info: dict[str, Any] = {
        "observed_obs": obs[observed].astype(np.float32),
        "observed_action_mps2": core.bank.gt_accel_mps2[core.episode, t][observed],
        "collision": bool(res.collision) if res else False,
        "error": res.error if res else "",
    }
    if res is not None:
        info.update(res.terms)
    return info


def register() -> None:
    """Register the gymnasium envs (idempotent): ``gymnasium.make(SECTION_ENV_ID,
    scenario=..., data=..., generator=...)``; ``ENV_ID``, the name the ring wing's env had
    until stop 25, is the same env (its demo with no arguments). ``gymnasium.make_vec(...,
    vectorization_mode="vector_entry_point")`` gives ``SectionHiddenVectorEnv``: every
    sub-env in one SUMO run (rings)."""
    entry = "macromicro_sumo.env.section_envs:make_section_hidden_env"
    vector = "macromicro_sumo.env.batched_envs:SectionHiddenVectorEnv"
    for env_id in (ENV_ID, SECTION_ENV_ID):
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry, vector_entry_point=vector)


register()

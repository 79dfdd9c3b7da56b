"""Stage II environment: the ring in SUMO, hidden vehicles driven by one shared policy.

``RingCore`` owns one running SUMO simulation and is reused across episodes (resets move
the vehicles with ``moveTo``; SUMO is never restarted). The gymnasium (one hidden vehicle)
and PettingZoo (K hidden vehicles) environments in ``envs.py`` wrap it.

Episode start: a held-in snapshot whose hidden vehicles were completed by the trained
generator (completions are precomputed in a batch, which is what Algorithm 3 does per
episode, only faster). Every step, each vehicle gets a speed command in speed mode 0
(applied exactly, no SUMO safety checks): hidden vehicles v' = max(0, v + a dt) with the
agent's acceleration clipped to [a_min, a_max], capped by the safety layer
(``policy.safety = "sumo"``, the default: ``safety_cap``, counted in
``RingCore.safety_capped``; ``"none"``: applied as asked); observed vehicles replay their
recorded ground-truth speeds, except where that would run them into their leader
(``keep_clear``: counted in ``RingCore.replay_overrides``). Leaders, spacings and
observations come from arc positions.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from macromicro_sumo.data.objective import MacroTarget, macro_reward, macro_terms
from macromicro_sumo.data.ring import GroundTruth, Snapshots, hide, run_arrays, snapshot_states
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.ring_sampler import complete
from macromicro_sumo.road.physics import OBSERVATION_FEATURES, lookahead_features, safe_speed
from macromicro_sumo.road.ring import RingGeometry, read_ring
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

CTRL_TYPE = "ctrl"
SAFETY = ("none", "sumo")  # hidden vehicles' safety layer: none, or ``safety_cap``
SAFETY_TOLERANCE_MPS = 0.01  # a cap lower than the command by more counts as acting


@dataclass(frozen=True)
class EpisodeBank:
    """Start states and recorded futures of many episodes; arrays over episodes (E, ...)."""

    arc0_m: np.ndarray  # (E, N) completed scene
    speed0_mps: np.ndarray  # (E, N)
    hidden: np.ndarray  # (E, N) bool
    psi: np.ndarray  # (E, 6)
    limits_mps: np.ndarray  # (E, n_edges)
    replay_speed_mps: np.ndarray  # (E, H + 1, N) recorded speeds (observed vehicles replay them)
    gt_accel_mps2: np.ndarray  # (E, H, N) recorded actions
    true_arc0_m: np.ndarray  # (E, N) the true scene (evaluation only)
    run: np.ndarray
    time_s: np.ndarray
    spacing_std_m: np.ndarray | None = None  # (E,) L_var's target when measured dispersion is on

    def __len__(self) -> int:
        return len(self.run)

    @classmethod
    def _from_fields(cls, banks: list[EpisodeBank], fn) -> EpisodeBank:
        """A bank whose every array field is ``fn`` of that field in ``banks``."""
        return cls(
            **{
                f: None if getattr(banks[0], f) is None else fn([getattr(b, f) for b in banks])
                for f in cls.__dataclass_fields__
            }
        )

    @classmethod
    def concat(cls, banks: list[EpisodeBank]) -> EpisodeBank:
        """The episodes of ``banks`` one after the other."""
        return cls._from_fields(banks, np.concatenate)

    def take(self, idx: np.ndarray) -> EpisodeBank:
        """The episodes ``idx`` only."""
        return self._from_fields([self], lambda a: a[0][idx])

    def completed_again(self, complete_fn, length_m: float) -> EpisodeBank:
        """The same episodes with the hidden vehicles completed anew by ``complete_fn``
        (``build_bank``'s), without rebuilding the scenes and recorded futures."""
        snaps = Snapshots(
            run=self.run,
            time_s=self.time_s,
            arc_m=self.true_arc0_m,
            speed_mps=self.speed0_mps,  # observed speeds are the recorded ones
            psi=self.psi,
            hidden=self.hidden,
            length_m=length_m,
            spacing_std_m=self.spacing_std_m,
        )
        arc, speed = complete_fn(snaps)
        return replace(self, arc0_m=arc, speed0_mps=speed)


def build_bank(
    sc: Scenario,
    gt: GroundTruth,
    runs: np.ndarray,
    complete_fn,
    k: int | tuple[int, int],
    seed: int,
    horizon: int | None = None,
) -> EpisodeBank:
    """Episodes from snapshots of ``runs`` with ``k`` hidden vehicles (a value or a range).

    ``complete_fn(snaps) -> (arc, speed)`` fills the hidden vehicles (the generator, or a
    baseline). Snapshots too close to the end of a run for ``horizon`` steps are dropped.
    """
    h = horizon or sc.policy.horizon
    states = snapshot_states(gt, sc, runs)
    arrays = {r: run_arrays(gt.trajectories, r) for r in np.unique(states.run)}
    keep, replay, accel = [], [], []
    for i, (r, t) in enumerate(zip(states.run, states.time_s, strict=True)):
        times, _, spd, _ = arrays[r]
        j = int(np.searchsorted(times, t - 1e-9))
        if j + h + 1 > len(times):
            continue
        keep.append(i)
        replay.append(spd[j : j + h + 1])
        accel.append(np.diff(spd[j : j + h + 1], axis=0) / sc.simulation.step_length_s)
    if not keep:
        raise UserError(f"{gt.folder}: no snapshot leaves {h} steps of recorded future")
    states = states.take(np.array(keep))
    rng = np.random.default_rng([seed, 31])
    kk = rng.integers(k[0], k[1] + 1, len(states)) if isinstance(k, tuple) else k
    snaps = hide(states, kk, rng)
    arc, speed = complete_fn(snaps)
    lim = gt.speed_limits.pivot(index="run", columns="edge_id", values="speed_limit_mps")
    geo_edges = sorted(lim.columns, key=lambda e: (len(e), e))
    return EpisodeBank(
        arc0_m=arc,
        speed0_mps=speed,
        hidden=snaps.hidden,
        psi=snaps.psi,
        limits_mps=lim.loc[snaps.run, geo_edges].to_numpy(),
        replay_speed_mps=np.array(replay),
        gt_accel_mps2=np.array(accel),
        true_arc0_m=states.arc_m,
        run=snaps.run,
        time_s=snaps.time_s,
        spacing_std_m=snaps.spacing_std_m,
    )


def standstill_spacing(sc: Scenario) -> float:
    """The shortest front-to-front spacing of the fleet at a stop [m]: vehicle length plus
    the smallest standstill gap its drivers keep."""
    return sc.fleet.length_m + sc.fleet.min_gap_m[0]


def generator_completion(net, sc: Scenario, seed: int):
    """``complete_fn`` for ``build_bank`` that runs the trained generator (Algorithm 3),
    with spacings of at least the standstill spacing and kinematically consistent speeds
    (``ring_sampler.complete``'s ``standstill_m``, ``brake_mps2``: the action bound's
    braking, ``headway_s``: the fleet's shortest time headway). On a dense ring (ring_sugiyama) Psi's bounds alone placed vehicles on top of
    each other and slow ones just ahead of fast ones; on the paper's ring neither binds."""
    standstill, brake = standstill_spacing(sc), -sc.bounds.accel_mps2[0]

    def fn(snaps: Snapshots) -> tuple[np.ndarray, np.ndarray]:
        comp = complete(
            net,
            snaps,
            sc.generator.t_max,
            seed,
            standstill_m=standstill,
            brake_mps2=brake,
            headway_s=sc.fleet.tau_s[0],
        )
        return comp.arc_m, comp.speed_mps

    return fn


def keep_clear(
    cmd: np.ndarray,
    observed: np.ndarray,
    leader: np.ndarray,
    spacing: np.ndarray,
    length_m: float,
    clear_m: float,
    brake_mps2: float,
    dt: float,
) -> np.ndarray:
    """Speed commands (N,) with every ``observed`` vehicle's capped to what lets it stop
    behind its leader braking at ``brake_mps2`` (as the leader could from its commanded
    speed), and to what keeps a bumper gap of ``clear_m`` after this step (positions advance
    by the commanded speed times ``dt``). Caps travel backwards along a queue of observed
    vehicles. The cap of the first rule, v <= -b dt + sqrt((b dt)^2 + v_l^2 + 2 b (spacing +
    v_l dt - length)), lets a vehicle brake in time where the second alone stops it dead in
    one step, harder than any follower behind it can.

    Why: an observed vehicle replays the speeds it drove behind its true leader. Behind a
    generated one, placed closer or driving slower, the replay does not react and runs into
    it (ring_sugiyama, idm_true, completions with safe speeds: 345 of 1,400 episodes at
    K = 1, 628 at K = 4). A replay that would come that close leaves its record and brakes.
    """
    room = (spacing - length_m - clear_m) / dt
    bdt = brake_mps2 * dt
    out = cmd
    for _ in range(len(cmd)):
        v_l = out[leader]
        stop = -bdt + np.sqrt(
            np.maximum(bdt**2 + v_l**2 + 2 * brake_mps2 * (spacing + v_l * dt - length_m), 0.0)
        )
        allow = np.maximum(np.minimum(v_l + room, stop), 0.0)
        over = observed & (out > allow)
        if not over.any():
            break
        out = np.where(over, allow, out)
    return out


def safety_cap(
    cmd: np.ndarray,
    hidden: np.ndarray,
    leader: np.ndarray,
    spacing: np.ndarray,
    speed: np.ndarray,
    length_m: float,
    clear_m: float,
    brake_mps2: float,
    dt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Speed commands (N,) with each ``hidden`` vehicle's capped at the Krauss/Gipps safe
    speed (``road.physics.safe_speed``) behind its leader, both braking at ``brake_mps2``
    (it one step later), keeping a bumper gap of ``clear_m``; and which it capped (by more
    than ``SAFETY_TOLERANCE_MPS``). A cap may brake harder than a_min, as SUMO's does.
    Why: a policy braking at 1.2-1.5 m/s^2 where more was needed ran into observed leaders
    braking as recorded (ring_sugiyama: 89-139 of 1,400 episodes per K, IDM methods 0).
    The leader brakes at |a_min| (symmetric: safe on the way to the stop too): a hidden one
    no harder by its action, the recording's drivers in 0.07% of ring_sugiyama's steps (its
    first seconds); the cap binds on no recorded command of either ring, where 2 |a_min|
    (``keep_clear``'s) capped 1% of ring_sugiyama's recorded vehicle-steps.
    """
    gap = spacing[hidden] - length_m - clear_m
    safe = safe_speed(gap, speed[leader[hidden]], brake_mps2, brake_mps2, dt)
    capped = np.zeros(len(cmd), dtype=bool)
    capped[hidden] = safe < cmd[hidden] - SAFETY_TOLERANCE_MPS
    out = cmd.copy()
    out[capped] = np.maximum(safe[capped[hidden]], 0.0)
    return out, capped


@dataclass
class StepResult:
    """What one step of a core (ring or section) returns."""

    obs: np.ndarray  # (N, d) every slot's observation
    r_macro: float
    terms: dict[str, float]
    collision: bool
    truncated: bool
    error: str
    active: np.ndarray  # (N,) bool: slots on the road after this step


class RingCore:
    """One SUMO ring reused for every episode; numpy state in, numpy state out."""

    def __init__(
        self,
        sc: Scenario,
        bank: EpisodeBank,
        seed: int = 0,
        fcd_file: Path | None = None,
        safety: str | None = None,
    ) -> None:
        # Training and evaluation alike, unless told (the recording replays with "none").
        safety = safety or sc.policy.safety
        if safety not in SAFETY:
            raise UserError(f"safety = {safety!r}: one of {', '.join(SAFETY)}")
        self.safety = safety
        self.sc = sc
        self.bank = bank
        self.geo: RingGeometry = read_ring(sc.resolve(sc.network.net_file))
        self.length = self.geo.length_m
        self.dt = sc.simulation.step_length_s
        self.a_min, self.a_max = sc.bounds.accel_mps2
        # The fleet of the episodes (N, or 2 for leader-follower tests): on a closed
        # one-lane road every slot is always on it, in lane 0.
        self.n = bank.arc0_m.shape[1]
        # Observed vehicles leave their record (``keep_clear``) only to keep half the
        # smallest standstill gap, or to stop in time braking at twice the action bound:
        # the recording never needs either (ring_sugiyama's comes no closer than 1.39 m of
        # 1.5 m, and brakes harder than |a_min| = 3 m/s^2 in its first seconds only, at
        # most 4.5), so true scenes replay as recorded (tested).
        self.clear_m = 0.5 * sc.fleet.min_gap_m[0]
        self.keep_clear_brake = -2.0 * self.a_min
        # Vehicle-steps on which an observed vehicle left its record, and the episodes.
        self.replay_overrides = 0
        self.overridden_episodes: set[int] = set()
        # Hidden vehicle-steps; those the safety layer capped (in all, last step's, episodes).
        self.hidden_steps = 0
        self.safety_capped = 0
        self.step_capped = np.zeros(self.n, dtype=bool)
        self.capped_episodes: set[int] = set()
        self.active = np.ones(self.n, dtype=bool)
        self.lane = np.zeros(self.n, dtype=np.int64)
        self.ids = [f"veh{i}" for i in range(self.n)]
        self._edge_index = {e: i for i, e in enumerate(self.geo.edge_ids)}
        self._tmp = tempfile.TemporaryDirectory(prefix="macromicro-env-")
        vtype = Path(self._tmp.name) / "ctrl.add.xml"
        # Speed-controlled vehicles: no car-following of their own matters (speed mode 0);
        # a high speedFactor lets SUMO accept any recorded speed at insertion.
        vtype.write_text(
            f'<additional><vType id="{CTRL_TYPE}" length="{sc.fleet.length_m:g}" minGap="0" '
            f'maxSpeed="60" speedFactor="3" speedDev="0" accel="10" decel="10" emergencyDecel="20"/></additional>'
        )
        adds = (sc.resolve(sc.network.routes_file), vtype)
        self.sim = Simulation(
            SumoOptions(sc.resolve(sc.network.net_file), adds, self.dt, seed, fcd_file=fcd_file)
        )
        self._broken = True
        self._insert_fleet()
        self._next = np.roll(np.arange(self.n), -1)
        self.obs_dim = len(OBSERVATION_FEATURES[sc.policy.observation])
        self.episode = -1
        self.t = 0
        self.arc = np.zeros(self.n)
        self.speed = np.zeros(self.n)
        self.limits = np.zeros(len(self.geo.edge_ids))

    def _insert_fleet(self) -> None:
        """(Re-)insert any vehicle SUMO does not have (at start, or after a lost vehicle)."""
        present = set(self.sim.vehicle_ids())
        missing = [i for i, vid in enumerate(self.ids) if vid not in present]
        if missing:
            spacing = self.length / self.n
            edges, pos = zip(*(self.geo.to_edge(i * spacing) for i in missing), strict=True)
            self.sim.add_vehicles(
                [self.ids[i] for i in missing],
                [f"r_{self.geo.edge_ids[e]}" for e in edges],
                [CTRL_TYPE] * len(missing),
                pos,
                [0.0] * len(missing),
            )
            self.sim.step()
        if len(self.sim.vehicle_ids()) != self.n:
            raise UserError(
                f"SUMO holds {len(self.sim.vehicle_ids())} of {self.n} vehicles after insertion"
            )
        self.sim.subscribe(self.ids)
        self.sim.set_speed_mode(self.ids, 0)
        self._broken = False

    def close(self) -> None:
        self.sim.close()
        self._tmp.cleanup()

    # ------------------------------------------------------------------ episode
    def reset(self, episode: int) -> np.ndarray:
        """Place the episode's completed scene in SUMO (no restart); returns observations."""
        b = self.bank
        self.episode = episode
        self.t = 0
        self.arc = b.arc0_m[episode].copy()
        self.speed = b.speed0_mps[episode].copy()
        self.hidden = b.hidden[episode]
        self.psi = b.psi[episode]
        std = None if b.spacing_std_m is None else b.spacing_std_m[episode]
        # Psi's columns (data.macro.PSI_COLUMNS): v_mean, d_mean, d_min, d_max, v_min, v_max.
        self._target = MacroTarget(*self.psi[:4], spacing_std_m=std)
        self.limits = b.limits_mps[episode]
        if not self.sim.is_active():  # another simulation took libsumo's one: ours again
            self.sim.reload()
            self._broken = True
        if self._broken:
            self._insert_fleet()
        self.sim.set_lane_speed_limits(self.geo.lane_ids, self.limits)
        self.edge = self.geo.edge_index(self.arc)
        pos = self.arc - self.geo.offsets_m[self.edge]
        self.sim.move_to(
            self.ids,
            [self.geo.lane_ids[e] for e in self.edge],
            pos,
            [f"r_{self.geo.edge_ids[e]}" for e in self.edge],
        )
        self._verify_first = True
        self._scene()
        return self.observations()

    def _scene(self) -> None:
        """Leader and front-to-front spacing of every vehicle, once per step (hot path)."""
        order = np.argsort(self.arc)
        s = self.arc[order]
        gaps = np.empty(self.n)
        gaps[:-1] = s[1:] - s[:-1]
        gaps[-1] = s[0] + self.length - s[-1]
        self.leader = np.empty(self.n, dtype=np.int64)
        self.leader[order] = order[self._next]
        self.spacing = np.empty(self.n)
        self.spacing[order] = gaps

    def observations(self) -> np.ndarray:
        """Per vehicle [v, v_limit, spacing, v - v_leader] (+ [next limit, distance] with
        ``policy.observation = "lookahead"``); see physics.OBSERVATION_FEATURES."""
        obs = np.empty((self.n, self.obs_dim))
        obs[:, 0] = self.speed
        obs[:, 1] = self.limits[self.edge]
        obs[:, 2] = self.spacing
        obs[:, 3] = self.speed - self.speed[self.leader]
        if self.obs_dim > 4:
            obs[:, 4], obs[:, 5] = lookahead_features(
                self.arc, self.edge, self.geo.offsets_m, self.geo.lengths_m, self.limits
            )
        return obs

    def macro_reward(self) -> tuple[float, dict[str, float]]:
        """r_macro,t of the whole scene against the episode's Psi (``data.objective``):
        every vehicle's speed, and the spacings that touch a hidden vehicle (it, or its
        leader) as A."""
        terms = macro_terms(
            self.speed,
            None,  # every slot of a ring is on it
            self.spacing[self.hidden | self.hidden[self.leader]],
            None,  # already the set A
            self._target,
            self.sc.policy.macro_speed_scale_mps,
        )
        terms = {k: float(v) for k, v in terms.items()}
        g = self.sc.generator
        return float(macro_reward(terms, g.lambda_v, g.lambda_d)), terms

    def step(self, accel_hidden: np.ndarray) -> StepResult:
        """Advance one step: hidden vehicles apply ``accel_hidden`` (K,), observed replay."""
        if not self.sim.is_active():
            raise UserError(
                "another SUMO simulation was started in this process; libsumo runs one per "
                "process: reset() starts this one's again"
            )
        if self.t >= self.bank.replay_speed_mps.shape[1] - 1:
            raise UserError(f"episode over after {self.t} steps: call reset()")
        a = np.clip(accel_hidden, self.a_min, self.a_max)
        cmd = self.bank.replay_speed_mps[self.episode, self.t + 1].copy()
        cmd[self.hidden] = np.maximum(0.0, self.speed[self.hidden] + a * self.dt)
        self.hidden_steps += int(self.hidden.sum())
        if self.safety == "sumo":  # before keep_clear: observed followers see the capped speed
            cmd, self.step_capped = safety_cap(
                cmd,
                self.hidden,
                self.leader,
                self.spacing,
                self.speed,
                self.sc.fleet.length_m,
                self.clear_m,
                -self.a_min,
                self.dt,
            )
            if self.step_capped.any():
                self.safety_capped += int(self.step_capped.sum())
                self.capped_episodes.add(self.episode)
        kept = keep_clear(
            cmd,
            ~self.hidden,
            self.leader,
            self.spacing,
            self.sc.fleet.length_m,
            self.clear_m,
            self.keep_clear_brake,
            self.dt,
        )
        if kept is not cmd:
            self.replay_overrides += int(np.add.reduce(kept != cmd))
            self.overridden_episodes.add(self.episode)
            cmd = kept
        try:
            self.sim.set_speeds(self.ids, cmd)
            self.sim.step()
            e, p, v = self.sim.read_states(self.ids, self._edge_index)
        except Exception as exc:  # a vehicle lost or a SUMO error: truncate, training goes on
            self._broken = True
            return StepResult(
                self.observations(),
                0.0,
                {},
                False,
                True,
                f"{type(exc).__name__}: {exc}",
                self.active,
            )
        prev_arc = self.arc
        self.edge = e
        self.arc = self.geo.offsets_m[e] + p
        self.speed = v
        self.t += 1
        error = ""
        if self._verify_first:  # the placement at reset, checked after its first step
            self._verify_first = False
            off = (
                np.mod(prev_arc + cmd * self.dt - self.arc + self.length / 2, self.length)
                - self.length / 2
            )
            if np.abs(off).max() > 0.01 or np.abs(v - cmd).max() > 0.01:
                error = f"insertion check failed: position off by {np.abs(off).max():.3f} m"
        self._scene()
        # Arc gaps decide collisions: SUMO also reports one when moveTo reorders vehicles at reset.
        collision = bool(self.spacing.min() < self.sc.fleet.length_m)
        r, terms = self.macro_reward()
        return StepResult(self.observations(), r, terms, collision, bool(error), error, self.active)

"""Stage II on a road section of the user's network: hidden vehicles driven by the shared policy.

``SectionCore`` owns one SUMO run of the user's network WITHOUT the user's demand (the net
plus our vehicle types) and is reused for every episode. The paper's ring is the
special case of one lane, a closed loop and a fixed fleet; here vehicles enter lanes of
different widths of road, change lanes and leave the section, and the number of vehicles
varies per episode (arrays are padded to N slots; ``valid`` and ``active`` say which count).
The episodes (``SectionBank``) and the observation are ``env/section_bank.py``'s.

Action Space
    One acceleration [m/s^2] per hidden vehicle (``bank.hidden[ep]`` order), clipped to
    ``sc.bounds.accel_mps2``; applied as a speed command v' = max(0, v + a dt): exactly
    (speed mode 0) with ``safety = "none"``, capped at SUMO's safe speed behind whatever
    SUMO sees ahead (``SAFE_MODE``) with ``safety = "sumo"`` (the default: the policy
    alone does not reach zero collisions at merges; ``counts["safety_capped"]``). Lane
    changes of hidden vehicles are SUMO's own lane-change model (its gap checks).
Observation Space
    Per slot, ``physics.OBSERVATION_FEATURES[sc.policy.observation]``: speed, the local
    limit on its lane, the spacing to the leader in its lane (``NO_LEADER_GAP_M`` with no
    leader; a lane end or a red/yellow signal's stop line is a standing leader), v -
    v_leader (0 with no leader) and, with ``"lookahead"``, the next edge's limit on its
    lane and the distance to that edge (on the last edge of an open section: its own
    limit and the distance to the section's end). Inactive slots are zeros.
Rewards
    r_macro = 1 / (1 + lambda_v L_speed + lambda_d L_dist) of the active vehicles against
    psi (``section_target``, ``section_macro_reward``).
Starting State
    The episode's completed scene (observed vehicles + generated hidden vehicles), inserted
    with ``vehicle.add`` at the exact lane and position; checked after the insertion step.
Episode End
    After H steps; earlier (``truncated``) on a SUMO error, a failed insertion, or when no
    vehicle is left on the section. A vehicle that leaves the section (or SUMO) becomes
    inactive and is removed. Observed vehicles replay their recorded lane and speed while
    that is safe (SUMO's safe speed caps them; a recorded lane change into a vehicle
    waits); one that had to deviate catches up by speed until it is on its record again
    (``env/section_replay.py``; ``off_record``, ``counts``); their record ends where they
    left the section in the ground truth. Collisions are counted and truncate the episode.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from macromicro_sumo.env.observation import StepResult
from macromicro_sumo.env.section_bank import (
    SectionBank,
    section_macro_reward,
    section_observations,
    section_target,
    set_sumo_limits,
    stop_points,
)
from macromicro_sumo.env.section_replay import (
    REPLAY_SPEED_FACTOR,
    REPLAY_SUFFIX,
    SAFE_SUFFIX,
    arc_lag,
    catch_up_speeds,
    junction_lane,
    junction_vias,
    safe_places,
    vtypes_xml,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.physics import OBSERVATION_FEATURES
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

POSITION_TOL_M = 0.01  # insertion and replay checks: a placement off by more is an error
EXACT_MODE = 0  # SUMO speed mode: a speed command applies exactly, no checks
# SUMO speed mode: a command is capped at the car-following model's safe speed behind
# whatever SUMO sees ahead on the vehicle's route (bit 0) and stops at a red light (bit 4);
# acceleration bounds are not imposed (bits 1, 2), so a safe command still applies exactly.
SAFE_MODE = 1 | 16
SAFETY = ("none", "sumo")  # hidden vehicles' safety layer: none, or SAFE_MODE
DEFAULT_SAFETY = "sumo"
SPEED_TOL_MPS = 1e-3  # a read speed this far below its command: SUMO capped it
COUNTERS = (
    "replay_vehicles",  # observed vehicles replayed (per episode)
    "replay_off_record",  # times an observed vehicle left its record (capped, refused move)
    "replay_returned",  # ... and came back onto it (position and lane)
    "replay_steps",  # observed vehicle-steps replayed
    "replay_capped",  # ... whose command SUMO's safe speed capped
    "replay_off_steps",  # ... that ended off their record
    "replay_lag_m",  # sum over those of |recorded - actual arc| (mean: / replay_off_steps)
    "replay_moves_refused",  # recorded lane changes / placements postponed: target unsafe
    "hidden_steps",  # hidden vehicle-steps commanded
    "safety_capped",  # ... whose command the safety layer capped (safety = "sumo")
)


# --------------------------------------------------------------------------- core


class SectionCore:
    """One SUMO run of the user's network (no demand) reused for every episode."""

    def __init__(
        self,
        sc,
        section: Section,
        bank: SectionBank,
        net_file: Path,
        seed: int = 0,
        fcd_file: Path | None = None,
        vclass: str = "passenger",
        safety: str | None = None,
        replay_min_gap_m: float | None = None,
    ) -> None:
        # Training and evaluation alike: the scenario's choice, else the safety layer (the
        # policy alone does not reach zero collisions on multi-lane sections, measured).
        safety = safety or getattr(sc.policy, "safety", DEFAULT_SAFETY)
        if safety not in SAFETY:
            raise UserError(f"safety = {safety!r}: one of {', '.join(SAFETY)}")
        self.safety = safety
        self.counts: dict[str, float] = dict.fromkeys(COUNTERS, 0) | {"replay_lag_m": 0.0}
        self.sc = sc
        self.section = section
        self.episode_section, self._sumo_limits = section, section.limits_mps  # see reset
        self.bank = bank
        self.dt = sc.simulation.step_length_s
        self.a_min, self.a_max = sc.bounds.accel_mps2
        self.n = bank.arc0_m.shape[1]
        self.observation = sc.policy.observation
        self.obs_dim = len(OBSERVATION_FEATURES[self.observation])
        self._tmp = tempfile.TemporaryDirectory(prefix="macromicro-section-env-")
        lengths = np.concatenate([bank.length_m[bank.valid], bank.true_length_m.ravel()])
        lengths = np.unique(np.round(lengths[np.isfinite(lengths) & (lengths > 0)], 2))
        self._vtype = {float(x): f"mm_L{i}" for i, x in enumerate(lengths)}
        vtypes = Path(self._tmp.name) / "vtypes.add.xml"
        vtypes.write_text(
            vtypes_xml(
                self._vtype,
                sc.bounds.accel_mps2,
                sc.bounds.min_gap_m,
                vclass,
                self.dt,
                replay_min_gap_m,
            )
        )
        self.sim = Simulation(
            SumoOptions(Path(net_file), (vtypes,), self.dt, seed, fcd_file=fcd_file)
        )
        self._routes = self._add_routes()
        self._has_lights = self.sim.has_traffic_lights()
        self._lanes = section.lanes
        self._via = junction_vias(section)
        self._resets = 0
        self.episode = -1
        self.t = 0
        self.ids: list[str] = []
        self.lane = np.zeros(self.n, dtype=np.int64)
        self.arc = np.zeros(self.n)
        self.speed = np.zeros(self.n)
        self.active = np.zeros(self.n, dtype=bool)
        self.hidden = np.zeros(self.n, dtype=bool)
        self.leader = np.full(self.n, -1, dtype=np.int64)
        self.spacing = np.full(self.n, NO_LEADER_GAP_M)
        # Observed vehicles off their record (a capped speed, a postponed lane change): they
        # catch up by speed (``catch_up_speeds``) until they are on it again.
        self.off_record = np.zeros(self.n, dtype=bool)
        self._obs = np.zeros((self.n, self.obs_dim))
        self._error = ""
        self.rewarded = True  # False: step returns r_macro = 0 (a rollout that records states)

    def _add_routes(self) -> list[str]:
        """One route per start edge to the section's end (a loop: laps for any episode)."""
        edges = list(self.section.edge_ids)
        laps = 1
        if self.section.closed:
            b = self.bank
            v = np.nanmax(
                np.concatenate([b.speed0_mps[b.valid], b.replay_speed_mps.ravel(), [1.0]])
            )
            reach = (v + self.a_max * b.horizon * self.dt) * b.horizon * self.dt
            laps = int(np.ceil(reach / self.section.length_m)) + 2
        ids = []
        for e in range(len(edges)):
            rid = f"mm_r{e}"
            self.sim.add_route(
                rid, (edges[e:] + edges[:e]) * laps if self.section.closed else edges[e:]
            )
            ids.append(rid)
        return ids

    def close(self) -> None:
        self.sim.close()
        self._tmp.cleanup()

    # ------------------------------------------------------------------ episode
    def reset(self, episode: int) -> np.ndarray:
        """Insert the episode's scene (no restart); returns the observations (N, obs_dim)."""
        if not self.sim.is_active():  # another simulation took libsumo's one: ours again
            self.sim.reload()
            self._routes = self._add_routes()
            self._sumo_limits = self.section.limits_mps
        b = self.bank
        sec = self.episode_section = b.section_of(self.section, episode)  # the run's limits
        self._sumo_limits = set_sumo_limits(self.sim, sec, self._sumo_limits)
        self.episode, self.t, self._error = episode, 0, ""
        self.sim.clear_vehicles()
        self._resets += 1
        self.ids = [f"m{self._resets}.{i}" for i in range(self.n)]
        self.hidden = b.hidden[episode]
        self.psi = b.psi[episode]
        self._target = section_target(self.psi)
        valid = b.valid[episode]
        slots = np.flatnonzero(valid)
        want = np.zeros(self.n)
        want_lane = np.zeros(self.n, dtype=np.int64)
        in_junction: dict[int, tuple[str, float, int]] = {}
        for i in slots:
            lane0, arc0 = int(b.lane0[episode, i]), float(b.arc0_m[episode, i])
            via = junction_lane(sec, self._via, lane0, arc0)
            if via is not None:
                # Inserted near the end of the edge before, then moved onto the junction's own
                # lane after the insertion step: stacking every vehicle of a junction at the
                # next edge's start crashes them (long junctions of a race track: 35 m).
                in_junction[i] = via[1:]
                e = via[0]
                lane_idx = min(lane0, int(sec.n_lanes[e]) - 1)
                pos = max(0.0, float(sec.lengths_m[e]) - 0.5)
            else:
                e, lane_idx, pos = sec.to_lane(lane0, arc0)
            want[i], want_lane[i] = sec.offsets_m[e] + pos, lane_idx
            if i in in_junction:
                want[i], want_lane[i] = arc0, lane0
            length = float(np.round(b.length_m[episode, i], 2))
            # SUMO refuses a departure above the lane's limit x the vType's speedFactor; the
            # env keeps the true speed. Under the safe-speed check a command may not exceed
            # the inserted speed + one step of accel: every replayed vehicle recorded above
            # the limit was held back in the first step (Bremen: 50 of 123 off their record).
            if not self.hidden[i]:
                suffix = REPLAY_SUFFIX
            else:
                suffix = "" if self.safety == "none" else SAFE_SUFFIX
            factor = 1.0 if suffix == "" else REPLAY_SPEED_FACTOR
            self.sim.add_vehicle(
                self.ids[i],
                self._routes[e],
                self._vtype[length] + suffix,
                lane_idx,
                pos,
                min(float(b.speed0_mps[episode, i]), factor * float(sec.limits_mps[e, lane_idx])),
            )
        self.sim.step()
        live = [self.ids[i] for i in slots]
        self.sim.subscribe_lanes(live)
        states = self.sim.read_lane_states()
        self.active = np.zeros(self.n, dtype=bool)
        self.lane = np.zeros(self.n, dtype=np.int64)
        self.arc = np.zeros(self.n)
        self.speed = np.where(valid, b.speed0_mps[episode], 0.0)
        worst = 0.0
        for i, (via_id, depth, lane_idx) in in_junction.items():
            try:
                self.sim.move_to_lanes([self.ids[i]], [via_id], [depth])
            except Exception as exc:  # SUMO refused: the episode is truncated, training goes on
                self._error = f"junction placement failed: {type(exc).__name__}: {exc}"
                continue
            self.active[i] = True
            self.lane[i] = lane_idx
            self.arc[i] = want[i]
        for i in slots:
            if i in in_junction:
                continue
            st = states.get(self.ids[i])
            hit = None if st is None else self._lanes.get(st[0])
            if hit is None:
                self._error = f"insertion failed: vehicle {i} is not on the section"
                continue
            self.active[i] = True
            self.lane[i] = hit[1]
            self.arc[i] = hit[2] + st[1] * hit[3]
            worst = max(worst, abs(self.arc[i] - want[i]), abs(hit[1] - want_lane[i]))
        if worst > POSITION_TOL_M and not self._error:
            self._error = f"insertion check failed: position off by {worst:.3f} m"
        self.off_record = np.zeros(self.n, dtype=bool)
        self.counts["replay_vehicles"] += int((valid & ~self.hidden).sum())
        # Observed vehicles replay their record only while it is safe (SAFE_MODE): the
        # hidden vehicles around them are not the recorded ones.
        hidden_mode = SAFE_MODE if self.safety == "sumo" else EXACT_MODE
        self.sim.set_speed_mode([self.ids[i] for i in slots if self.hidden[i]], hidden_mode)
        self.sim.set_speed_mode([self.ids[i] for i in slots if not self.hidden[i]], SAFE_MODE)
        self.sim.set_lane_change_mode([self.ids[i] for i in slots if not self.hidden[i]], 0)
        self._scene()
        return self._obs.copy()

    def _scene(self) -> None:
        """Leaders, spacings and observations of the active vehicles (one sort); a red or
        yellow signal ahead is a standing leader at its stop line."""
        stop_lane = stop_arc = None
        if self._has_lights:
            live = np.flatnonzero(self.active)
            dist = np.fmin(self.sim.stop_lines_m([self.ids[i] for i in live]), np.inf)  # NaN: inf
            stop_lane, stop_arc = stop_points(self.section, self.lane[live], self.arc[live], dist)
        self._obs, self.leader, self.spacing = section_observations(
            self.episode_section,
            self.lane,
            self.arc,
            self.speed,
            self.active,
            self.observation,
            stop_lane,
            stop_arc,
            self.bank.factor_of(self.episode),  # each driver's own limits (policy.driver_speed)
        )

    def observations(self) -> np.ndarray:
        return self._obs.copy()

    def macro_reward(self) -> tuple[float, dict[str, float]]:
        g = self.sc.generator
        return section_macro_reward(
            self.speed,
            self.spacing,
            self.leader,
            self.hidden,
            self.active,
            self._target,
            g.lambda_v,
            g.lambda_d,
            self.sc.policy.macro_speed_scale_mps,
        )

    def _result(self, r: float, terms, collision: bool, truncated: bool, error: str):
        return StepResult(
            self._obs.copy(), r, terms, collision, truncated, error, self.active.copy()
        )

    def step(self, accel_hidden: np.ndarray) -> StepResult:
        """Advance one step: hidden vehicles apply ``accel_hidden`` (one per hidden slot,
        inactive ones ignored), observed vehicles replay their records."""
        if not self.sim.is_active():
            raise UserError(
                "another SUMO simulation was started in this process; libsumo runs one per "
                "process: reset() starts this one's again"
            )
        b = self.bank
        if self.t >= b.horizon:
            raise UserError(f"episode over after {self.t} steps: call reset()")
        if self._error:
            return self._result(0.0, {}, False, True, self._error)
        ep, t = self.episode, self.t
        cmd = np.zeros(self.n)
        a = np.minimum(np.maximum(accel_hidden, self.a_min), self.a_max)  # np.clip, faster
        cmd[self.hidden] = np.maximum(0.0, self.speed[self.hidden] + a * self.dt)
        obs_slots = self.active & ~self.hidden
        rv = b.replay_speed_mps[ep, t + 1]
        gone = obs_slots & np.isnan(rv)
        if gone.any():  # the recorded vehicle left the section: it leaves the episode
            self.active &= ~gone
            self.sim.remove_vehicles([self.ids[i] for i in np.flatnonzero(gone)])
        replay = obs_slots & ~gone
        cmd[replay] = rv[replay]
        back = np.flatnonzero(replay & self.off_record)
        if back.size:
            cmd[back] = catch_up_speeds(
                self.speed[back],
                rv[back],
                b.replay_arc_m[ep, t + 1, back],
                self.arc[back],
                arc_lag(self.section, b.replay_arc_m[ep, t, back], self.arc[back]),
                self.dt,
                (self.a_min, self.a_max),
            )
        live = np.flatnonzero(self.active)
        try:
            self.sim.set_speeds([self.ids[i] for i in live], cmd[live])
            self.sim.step()
            states = self.sim.read_lane_states()
            collision = self.sim.collisions() > 0
        except Exception as exc:  # a SUMO error: truncate, training goes on
            return self._result(0.0, {}, False, True, f"{type(exc).__name__}: {exc}")
        self._count_caps(live, cmd, replay, states)
        lanes, left = self._lanes, []
        for i in live:
            st = states.get(self.ids[i])
            if st is None:  # arrived at the end of its route: off the open end
                self.active[i] = False
                continue
            hit = lanes.get(st[0])
            if hit is None:
                if st[0].startswith(":"):  # an internal lane the section does not map
                    self.arc[i] += st[2] * self.dt
                    self.speed[i] = st[2]
                    continue
                self.active[i] = False
                left.append(self.ids[i])
                continue
            self.lane[i] = hit[1]
            self.arc[i] = hit[2] + st[1] * hit[3]
            self.speed[i] = st[2]
        if left:
            self.sim.remove_vehicles(left)
        self._rejoin(replay, b.replay_lane[ep, t + 1], b.replay_arc_m[ep, t + 1])
        error = self._follow_records(replay, b.replay_lane[ep, t + 1], b.replay_arc_m[ep, t + 1])
        self.t += 1
        self._scene()
        if error or not self.active.any():
            return self._result(0.0, {}, collision, True, error)
        r, terms = self.macro_reward() if self.rewarded else (0.0, {})
        return self._result(r, terms, collision, False, "")

    def _count_caps(self, live: np.ndarray, cmd: np.ndarray, replay: np.ndarray, states) -> None:
        """Count the commands SUMO's safe speed capped; a capped observed vehicle is off
        its record from now on."""
        read = np.full(self.n, np.nan)
        for i in live:
            st = states.get(self.ids[i])
            if st is not None:
                read[i] = st[2]
        with np.errstate(invalid="ignore"):
            capped = read < cmd - SPEED_TOL_MPS
        hid = np.zeros(self.n, dtype=bool)
        hid[live] = self.hidden[live]
        self.counts["replay_steps"] += int(replay.sum())
        self.counts["replay_capped"] += int((capped & replay).sum())
        self.counts["hidden_steps"] += int(hid.sum())
        if self.safety != "none":
            self.counts["safety_capped"] += int((capped & hid).sum())
        self._leave_record(capped & replay)

    def _rejoin(self, replay: np.ndarray, lane: np.ndarray, arc_m: np.ndarray) -> None:
        """Vehicles that caught up with their record (position within ``POSITION_TOL_M``,
        the recorded lane) are on it again; count the others' lag."""
        off = replay & self.active & self.off_record
        if not off.any():  # the usual step: nobody to rejoin, no lag to count
            return
        lag = np.abs(arc_lag(self.section, arc_m, self.arc))
        back = off & (lag <= POSITION_TOL_M) & (lane == self.lane)
        self.off_record &= ~back
        self.counts["replay_returned"] += int(back.sum())
        still = off & ~back
        self.counts["replay_off_steps"] += int(still.sum())
        self.counts["replay_lag_m"] += float(lag[still].sum())

    def _leave_record(self, mask: np.ndarray) -> None:
        self.counts["replay_off_record"] += int((mask & ~self.off_record).sum())
        self.off_record |= mask

    def _follow_records(self, replay: np.ndarray, lane: np.ndarray, arc_m: np.ndarray) -> str:
        """Put observed vehicles where the record says (a recorded lane change, or drift),
        if that place is safe now; returns an error text if SUMO refuses.

        A vehicle off its record (its speed was capped) keeps its own arc, catching up by
        speed: only its recorded lane is applied, where the record is on the same edge. A
        target place that would cut in too close to the vehicles there waits (counted).
        """
        sec = self.section
        on_record = replay & self.active & ~self.off_record
        off = self.arc - arc_m
        if sec.closed:
            off = np.mod(off + sec.length_m / 2, sec.length_m) - sec.length_m / 2
        behind = replay & self.active & self.off_record & (lane != self.lane)
        if behind.any():  # only where the record is on the same edge (two node lookups)
            behind &= sec.node_of(arc_m)[0] == sec.node_of(self.arc)[0]
        want_arc = np.where(replay & self.active & self.off_record, self.arc, arc_m)
        fix = np.flatnonzero(
            (on_record & ((lane != self.lane) | (np.abs(off) > POSITION_TOL_M))) | behind
        )
        if not fix.size:
            return ""
        act = np.flatnonzero(self.active)
        ok = safe_places(
            sec,
            self.lane[act],
            self.arc[act],
            self.speed[act],
            self.bank.length_m[self.episode, act],
            np.searchsorted(act, fix),
            lane[fix].astype(np.int64),
            want_arc[fix],
            self.dt,
            self.a_min,
            self.sc.bounds.min_gap_m,
        )
        self.counts["replay_moves_refused"] += int((~ok).sum())
        refused = np.zeros(self.n, dtype=bool)
        refused[fix[~ok]] = True
        self._leave_record(refused)
        fix = fix[ok]
        if not fix.size:
            return ""
        places = [self.section.to_lane(int(lane[i]), float(want_arc[i])) for i in fix]
        try:
            self.sim.move_to(
                [self.ids[i] for i in fix],
                [f"{sec.edge_ids[e]}_{k}" for e, k, _ in places],
                [p for _, _, p in places],
                [self._routes[e] for e, _, _ in places],
            )
        except Exception as exc:
            return f"{type(exc).__name__}: {exc}"
        for i, (e, k, p) in zip(fix, places, strict=True):
            self.lane[i], self.arc[i] = k, sec.offsets_m[e] + p
        return ""

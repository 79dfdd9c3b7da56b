"""Stage II on a road section of the user's network: hidden vehicles driven by the shared policy.

``SectionCore`` owns one SUMO run of the user's network WITHOUT the user's demand (the net
plus our vehicle types) and is reused for every episode. The paper's ring is the
special case of one lane, a closed loop and a fixed fleet; here vehicles enter lanes of
different widths of road, change lanes and leave the section, and the number of vehicles
varies per episode (arrays are padded to N slots; ``valid`` and ``active`` say which count).
The episodes (``SectionBank``) and the observation are ``env/section_bank.py``'s.

Action Space
    One acceleration [m/s^2] per hidden vehicle (``bank.hidden[ep]`` order), clipped to
    ``sc.bounds.accel_mps2`` and at most the slot's vType accel, applied as a speed command
    v' = max(0, v + a dt) at most its vType maxSpeed (``SectionBank.accel_mps2``,
    ``vmax_mps``: its physics, by the deployment's rule, ``road.vtype``): exactly
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
    limit and the distance to the section's end); with ``"lookahead_length"`` then its own
    length (the slot's vehicle's). The ``"lookahead_gap"`` layouts observe the bumper-to-bumper
    gap (the leader's own length) in place of the spacing. Inactive slots are zeros.
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

from pathlib import Path

import numpy as np

from macromicro_sumo.env.observation import StepResult
from macromicro_sumo.env.section_bank import (
    SectionBank,
    section_macro_reward,
    section_target,
    set_sumo_limits,
)
from macromicro_sumo.env.section_observations import section_observations, stop_points
from macromicro_sumo.env.section_replay import junction_lane, junction_vias
from macromicro_sumo.env.slot_core import DEFAULT_SAFETY, POSITION_TOL_M, SlotCore
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section
from macromicro_sumo.sumo.inputs import scenario_inputs, signal_programs
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

__all__ = ["DEFAULT_SAFETY", "SectionCore"]  # the default, importable from here as before


# --------------------------------------------------------------------------- core


class SectionCore(SlotCore):
    """One SUMO run of the user's network (no demand) reused for every episode."""

    _reward_fn = staticmethod(section_macro_reward)  # ``SlotCore.macro_reward``

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
        vtypes = self._setup(sc, bank, safety, vclass, replay_min_gap_m)
        self.section = section
        self.episode_section, self._sumo_limits = section, section.limits_mps  # see reset
        # The user's signal programs too: a reset puts each signal on the program the truth
        # recorded, which may be one of theirs rather than the net's.
        programs = signal_programs(scenario_inputs(sc), Path(self._tmp.name) / "signals.add.xml")
        self.sim = Simulation(
            SumoOptions(Path(net_file), (vtypes, *programs), self.dt, seed, fcd_file=fcd_file)
        )
        self._add_routes(np.array(section.edge_ids, dtype=object))
        self._index_lanes([str])
        self._has_lights = self.sim.has_traffic_lights()
        self._via = junction_vias(section)
        self._resets = 0
        self.episode = -1
        self.t = 0
        self.ids = np.full(self.n, "", dtype=object)
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

    # ------------------------------------------------------------------ episode
    def reset(self, episode: int) -> np.ndarray:
        """Insert the episode's scene (no restart); returns the observations (N, obs_dim)."""
        if not self.sim.is_active():  # another simulation took libsumo's one: ours again
            self.sim.reload()
            self._add_routes(self._edge_ids)
            self._sumo_limits = self.section.limits_mps
        b = self.bank
        sec = self.episode_section = b.section_of(self.section, episode)  # the run's limits
        self._sumo_limits = set_sumo_limits(self.sim, sec, self._sumo_limits)
        self.episode, self.t, self._error = episode, 0, ""
        self.sim.clear_vehicles()
        if b.signals is not None:  # as the truth's at the snapshot, after the insertion step
            self.sim.set_signal_states([(*r[:3], r[3] + self.dt) for r in b.signals[episode]])
        self._resets += 1
        self.ids = np.array([f"m{self._resets}.{i}" for i in range(self.n)], dtype=object)
        self.hidden = b.hidden[episode]
        self.psi = b.psi[episode]
        self._target = section_target(self.psi)
        valid = b.valid[episode]
        slots = np.flatnonzero(valid)
        want = np.zeros(self.n)
        want_lane = np.zeros(self.n, dtype=np.int64)
        in_junction: dict[int, tuple[str, float, int]] = {}
        suffix, factor = self._insert_kinds(self.hidden)
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
            self.sim.add_vehicle(
                self.ids[i],
                self._route_ids[e],
                self._vtype[length] + suffix[i],
                lane_idx,
                pos,
                min(
                    float(b.speed0_mps[episode, i]), factor[i] * float(sec.limits_mps[e, lane_idx])
                ),
            )
        self.sim.step()
        on, lane, arc, _, _ = self._read(valid)
        self.active = np.zeros(self.n, dtype=bool)
        self.lane = np.zeros(self.n, dtype=np.int64)
        self.arc = np.zeros(self.n)
        self.speed = np.where(valid, b.speed0_mps[episode], 0.0)
        for i, (via_id, depth, lane_idx) in in_junction.items():
            try:
                self.sim.move_to_lanes([self.ids[i]], [via_id], [depth])
            except Exception as exc:  # SUMO refused: the episode is truncated, training goes on
                self._error = f"junction placement failed: {type(exc).__name__}: {exc}"
                continue
            self.active[i] = True
            self.lane[i] = lane_idx
            self.arc[i] = want[i]
        check = valid.copy()
        check[list(in_junction)] = False
        for i in np.flatnonzero(check & ~on):
            self._error = f"insertion failed: vehicle {i} is not on the section"
        found = check & on
        self.active |= found
        self.lane[found], self.arc[found] = lane[found], arc[found]
        worst = max(
            np.abs(arc - want)[found].max(initial=0.0),
            np.abs(lane - want_lane)[found].max(initial=0),
        )
        if worst > POSITION_TOL_M and not self._error:
            self._error = f"insertion check failed: position off by {worst:.3f} m"
        self.off_record = np.zeros(self.n, dtype=bool)
        self._set_modes(valid)
        self._scene()
        return self._obs.copy()

    def _scene(self) -> None:
        """Leaders, spacings and observations of the active vehicles (one sort); a red or
        yellow signal ahead is a standing leader at its stop line, and so is, for a hidden
        vehicle (the section's route), the end of a lane that leaves the section; observed
        vehicles replay their own routes (a turner leaves the section there)."""
        stop_lane = stop_arc = None
        if self._has_lights:
            live = np.flatnonzero(self.active)
            lines = self.sim.stop_lines([self.ids[i] for i in live])
            dist = np.fmin(lines.dist_m, np.inf)  # NaN: inf
            stop_lane, stop_arc = stop_points(
                self.section, self.lane[live], self.arc[live], dist, lines.lanes
            )
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
            self.bank.length_m[self.episode],
            self.hidden,  # the driven ones drive the section's route: its lane ends
            **self.bank.gaps_of(self.episode),  # each vType's minGap, jmStoplineGap
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
        if self.t >= self.bank.horizon:
            raise UserError(f"episode over after {self.t} steps: call reset()")
        if self._error:
            return self._result(0.0, {}, False, True, self._error)
        accel_hidden = np.asarray(accel_hidden)
        accel = np.zeros(self.n, dtype=accel_hidden.dtype)  # its dtype: the same clipping
        accel[self.hidden] = accel_hidden
        try:
            cmd, replay, live = self._drive(accel, True, self.episode, self.t)
            state = self._read(live)
            collision = self.sim.collisions() > 0
        except Exception as exc:  # a SUMO error: truncate, training goes on
            return self._result(0.0, {}, False, True, f"{type(exc).__name__}: {exc}")
        error = self._after(live, cmd, replay, state, self.episode, self.t).get((), "")
        self.t += 1
        self._scene()
        if error or not self.active.any():
            return self._result(0.0, {}, collision, True, error)
        r, terms = self.macro_reward() if self.rewarded else (0.0, {})
        return self._result(r, terms, collision, False, "")

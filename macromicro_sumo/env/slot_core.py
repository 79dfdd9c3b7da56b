"""The step both env cores share: commands, SUMO's step and read, the replay bookkeeping.

``SectionCore`` (``env/section.py``: one scene of any section) and ``BatchedSectionCore``
(``env/batched.py``: B scenes of a ring in one SUMO run of B network copies) hold their
vehicles in slot arrays, (N,) and (B, N). ``SlotCore`` is the one implementation of what a
step does to them, written over any leading shape: the hidden vehicles' speed commands and
the observed vehicles' replay (``catch_up_speeds`` off their record), SUMO's step, the
read-back onto the section's arc, the counters, and the replay's rejoin and recorded moves.
What differs stays with each core: insertion (a general section's junction placements
against a loop's vectorised one), leaders and observations (``section_observations``
against ``loop_observations``), how a step ends. The per-scene work that needs a Python
loop (``safe_places``, SUMO's moveTo) runs per leading index (``np.ndindex``), as often
as the scenes that need it.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from itertools import repeat
from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.env.section_replay import (
    REPLAY_SPEED_FACTOR,
    REPLAY_SUFFIX,
    SAFE_SUFFIX,
    arc_lag,
    catch_up_speeds,
    safe_places,
    vtypes_xml,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.physics import OBSERVATION_FEATURES
from macromicro_sumo.road.section import Section
from macromicro_sumo.road.vtype import accel_limit, command_speeds
from macromicro_sumo.sumo.simulation import Simulation

Mask = np.ndarray  # (..., N) bool over the slots
Index = np.ndarray | int  # per scene: a bank episode, a step (one scene: an int)
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


class SlotCore:
    """Slot state and per-step work of an env core, over slot arrays (..., N)."""

    sim: Simulation
    section: Section
    bank: SectionBank
    ids: np.ndarray  # (..., N) object: SUMO's vehicle IDs
    episode: np.ndarray | int  # bank index per scene
    lane: np.ndarray  # (..., N) lane index on its edge
    arc: np.ndarray  # (..., N) position on the section's arc [m]
    speed: np.ndarray  # (..., N) [m/s]
    active: np.ndarray  # (..., N) bool: on the road
    hidden: np.ndarray  # (..., N) bool: driven by the policy (else replayed)
    off_record: np.ndarray  # (..., N) bool: an observed vehicle off its record
    _obs: np.ndarray  # (..., N, obs_dim) the observations after the last step
    _reward_fn: Callable[..., tuple[Any, dict[str, Any]]]  # the core's reward over (..., N)
    _target: Any  # what ``_reward_fn`` compares with: one MacroTarget, or psi (B, fields)
    _edge_ids: np.ndarray  # (..., E) each scene's SUMO edge IDs of the section
    _route_ids: np.ndarray  # (..., E) each scene's route from edge e on

    def _setup(
        self,
        sc,
        bank: SectionBank,
        safety: str | None,
        vclass: str,
        replay_min_gap_m: float | None,
        vtypes_file: Path | None = None,
    ) -> Path:
        """The settings both cores read; writes the vTypes file (``vtypes_file``'s text,
        else ``vtypes_xml``'s) into a fresh folder and returns its path."""
        # Training and evaluation alike: the scenario's choice, else the safety layer (the
        # policy alone does not reach zero collisions on multi-lane sections, measured).
        safety = safety or getattr(sc.policy, "safety", DEFAULT_SAFETY)
        if safety not in SAFETY:
            raise UserError(f"safety = {safety!r}: one of {', '.join(SAFETY)}")
        self.safety, self.sc, self.bank = safety, sc, bank
        self.counts: dict[str, float] = dict.fromkeys(COUNTERS, 0) | {"replay_lag_m": 0.0}
        self.dt = sc.simulation.step_length_s
        self.a_min, self.a_max = sc.bounds.accel_mps2
        self.n = bank.arc0_m.shape[1]
        self.observation = sc.policy.observation
        self.obs_dim = len(OBSERVATION_FEATURES[self.observation])
        self.rewarded = True  # False: steps return r_macro = 0 (a rollout that records states)
        self._tmp = tempfile.TemporaryDirectory(prefix="macromicro-env-")
        lengths = np.concatenate([bank.length_m[bank.valid], bank.true_length_m.ravel()])
        lengths = np.unique(np.round(lengths[np.isfinite(lengths) & (lengths > 0)], 2))
        self._vtype = {float(x): f"mm_L{i}" for i, x in enumerate(lengths)}
        path = Path(self._tmp.name) / "vtypes.add.xml"
        path.write_text(
            Path(vtypes_file).read_text()
            if vtypes_file is not None
            else vtypes_xml(
                self._vtype, sc.bounds.accel_mps2, sc.bounds.min_gap_m, vclass, self.dt,
                replay_min_gap_m,
            )
        )  # fmt: skip
        return path

    def close(self) -> None:
        self.sim.close()
        self._tmp.cleanup()

    def observations(self) -> np.ndarray:
        return self._obs.copy()

    def macro_reward(self) -> tuple[Any, dict[str, Any]]:
        """r_macro and its named terms of the active vehicles against each scene's target
        (``_reward_fn``: ``section_macro_reward`` for one scene, ``batch_macro_reward`` for
        B, per row)."""
        g = self.sc.generator
        return self._reward_fn(
            self.speed, self.spacing, self.leader, self.hidden, self.active, self._target,
            g.lambda_v, g.lambda_d, self.sc.policy.macro_speed_scale_mps,
        )  # fmt: skip

    def _add_routes(self, edge_ids: np.ndarray) -> None:
        """Per scene, one route per start edge to the section's end (a loop: laps for any
        episode); ``edge_ids`` (..., E): each scene's SUMO edges. Sets ``_route_ids``."""
        self._edge_ids = edge_ids
        laps = 1
        if self.section.closed:
            b = self.bank
            v = np.nanmax(
                np.concatenate([b.speed0_mps[b.valid], b.replay_speed_mps.ravel(), [1.0]])
            )
            reach = (v + self.a_max * b.horizon * self.dt) * b.horizon * self.dt
            laps = int(np.ceil(reach / self.section.length_m)) + 2
        self._route_ids = np.full(edge_ids.shape, "", dtype=object)
        closed = self.section.closed
        for row in np.ndindex(edge_ids.shape[:-1]):
            edges = list(edge_ids[row])
            for e in range(len(edges)):
                rid = "mm_r" + "_".join(map(str, (*row, e)))  # one scene: mm_r<e>
                self.sim.add_route(rid, (edges[e:] + edges[:e]) * laps if closed else edges[e:])
                self._route_ids[(*row, e)] = rid

    def _index_lanes(self, renames: list[Callable[[str], str]]) -> None:
        """Lane ID -> row of (lane index, arc of its start, arc per metre) of the section's
        lanes in every scene (``renames``: the original lane ID -> scene b's; the tables'
        last row: off the section)."""
        rows = [(f(lid), v) for f in renames for lid, v in self.section.lanes.items()]
        self._lane_code = {lid: k for k, (lid, _) in enumerate(rows)}
        self._lane_index = np.array([v[1] for _, v in rows] + [0], dtype=np.int64)
        self._lane_start = np.array([v[2] for _, v in rows] + [0.0])
        self._lane_scale = np.array([v[3] for _, v in rows] + [1.0])

    def _insert_kinds(self, hidden: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """vType suffix of each slot and the factor on the limit its departure speed may
        reach: SUMO refuses a departure above the lane's limit x the vType's speedFactor,
        and under the safe-speed check a command may not exceed the inserted speed + one
        step of accel (every replayed vehicle recorded above the limit was held back in the
        first step: Bremen, 50 of 123 off their record); the env keeps the true speed."""
        sfx = np.where(hidden, "" if self.safety == "none" else SAFE_SUFFIX, REPLAY_SUFFIX)
        return sfx, np.where(sfx == "", 1.0, REPLAY_SPEED_FACTOR)

    def _set_modes(self, slots: np.ndarray) -> None:
        """Speed and lane-change modes of the vehicles just inserted in ``slots``: observed
        ones replay their record only while it is safe (SAFE_MODE), since the hidden
        vehicles around them are not the recorded ones."""
        hid, obs = slots & self.hidden, slots & ~self.hidden
        self.counts["replay_vehicles"] += int(obs.sum())
        mode = SAFE_MODE if self.safety == "sumo" else EXACT_MODE
        self.sim.set_speed_mode(self.ids[hid].tolist(), mode)
        self.sim.set_speed_mode(self.ids[obs].tolist(), SAFE_MODE)
        self.sim.set_lane_change_mode(self.ids[obs].tolist(), 0)

    # ------------------------------------------------------------------ step
    def _drive(
        self, accel: np.ndarray, run: np.ndarray | bool, ep: Index, t: Index
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Speed commands of the vehicles of running scenes (``run`` broadcast to the
        slots): hidden ones apply ``accel`` (..., N), observed ones replay step t + 1 of
        their record (catching up where off it; a record that ended: the vehicle leaves the
        episode and SUMO); sets them and steps SUMO. Returns (cmd, replay, live) masks."""
        bk = self.bank
        # At most the vType's maxSpeed and accel, its physics, by the deployment's rule
        # (``road.vtype``): SUMO does not hold a command to either under these speed modes.
        # The accel of the hidden slots only (observed ones replay): where none of theirs is
        # below the bound, the bound alone (a scalar: a float32 action clipped as before).
        a_max = self.a_max
        if bk.accel_mps2 is not None:
            a_max = accel_limit(a_max, np.where(self.hidden, bk.accel_mps2[ep], np.inf))
        vmax = np.inf if bk.vmax_mps is None else bk.vmax_mps[ep]
        hid = command_speeds(self.speed, accel, self.dt, self.a_min, a_max, vmax)
        cmd = np.where(self.hidden & run, hid, 0.0)
        obs_slots = self.active & ~self.hidden & run
        rv = bk.replay_speed_mps[ep, t + 1]
        gone = obs_slots & np.isnan(rv)
        if gone.any():  # the recorded vehicle left the section: it leaves the episode
            self.active &= ~gone
            self.sim.remove_vehicles(self.ids[gone].tolist())
        replay = obs_slots & ~gone
        cmd = np.where(replay, rv, cmd)
        back = replay & self.off_record
        if back.any():
            cmd[back] = catch_up_speeds(
                self.speed[back],
                rv[back],
                bk.replay_arc_m[ep, t + 1][back],
                self.arc[back],
                arc_lag(self.section, bk.replay_arc_m[ep, t][back], self.arc[back]),
                self.dt,
                (self.a_min, self.a_max),
            )
        live = self.active & run
        self.sim.set_speeds(self.ids[live].tolist(), cmd[live])
        self.sim.step()
        return cmd, replay, live

    def _read(self, slots: np.ndarray) -> tuple[np.ndarray, ...]:
        """(on the section's lanes, lane, arc, speed: NaN where not in SUMO, on a junction's
        internal lane the section does not map) of the vehicles in ``slots`` (..., N); one
        on any other lane has left the section, and leaves SUMO."""
        ids = self.ids[slots].tolist()
        try:
            lanes, pos, spd = self.sim.lane_states(ids)
        except KeyError:  # one arrived at its route's end (an open section): read the others
            there = set(self.sim.vehicle_ids())
            keep = np.array([v in there for v in ids], dtype=bool)
            got = self.sim.lane_states([v for v, k in zip(ids, keep, strict=True) if k])
            lanes, pos, spd = [""] * len(ids), np.zeros(len(ids)), np.full(len(ids), np.nan)
            for k, x in zip(np.flatnonzero(keep), got[0], strict=True):
                lanes[k] = x
            pos[keep], spd[keep] = got[1], got[2]
        code = np.fromiter(map(self._lane_code.get, lanes, repeat(-1)), np.int64, len(lanes))
        on = np.zeros(slots.shape, dtype=bool)
        inner = np.zeros(slots.shape, dtype=bool)
        lane = np.zeros(slots.shape, dtype=np.int64)
        arc = np.zeros(slots.shape)
        speed = np.full(slots.shape, np.nan)
        on[slots], lane[slots] = code >= 0, self._lane_index[code]
        arc[slots] = self._lane_start[code] + pos * self._lane_scale[code]
        speed[slots] = spd
        if (code < 0).any():  # pending (lane ""), internal, or off the section
            idx = np.flatnonzero(code < 0)
            off = [k for k in idx.tolist() if lanes[k]]
            flat = np.zeros(len(ids), dtype=bool)
            flat[[k for k in off if lanes[k].startswith(":")]] = True
            inner[slots] = flat
            stray = [ids[k] for k in off if not lanes[k].startswith(":")]
            if stray:
                self.sim.remove_vehicles(stray)
        return on, lane, arc, speed, inner

    def _after(
        self, live: Mask, cmd: np.ndarray, replay: Mask, state: tuple, ep: Index, t: Index
    ) -> dict[tuple, str]:
        """The read-back of a step (``state``: ``_read`` of at least ``live``): counters,
        new positions (a vehicle off the section's lanes is inactive; on a junction's
        internal lane it moves on by its speed), the replay's rejoin and recorded moves.
        Returns the scenes (leading indices) whose moves SUMO refused, with the error."""
        on, lane, arc, read, inner = state
        self._count_caps(live, cmd, replay, read)
        on, inner = live & on, live & inner
        self.active &= ~live | on | inner
        self.lane = np.where(on, lane, self.lane)
        self.arc = np.where(on, arc, np.where(inner, self.arc + read * self.dt, self.arc))
        self.speed = np.where(on | inner, read, self.speed)
        rec_lane, rec_arc = self.bank.replay_lane[ep, t + 1], self.bank.replay_arc_m[ep, t + 1]
        self._rejoin(replay, rec_lane, rec_arc)
        return self._follow_records(replay, rec_lane, rec_arc)

    def _count_caps(self, live: Mask, cmd: np.ndarray, replay: Mask, read: np.ndarray) -> None:
        """Count the commands SUMO's safe speed capped; a capped observed vehicle is off
        its record from now on."""
        with np.errstate(invalid="ignore"):
            capped = live & (read < cmd - SPEED_TOL_MPS)
        hid = live & self.hidden
        self.counts["replay_steps"] += int(replay.sum())
        self.counts["replay_capped"] += int((capped & replay).sum())
        self.counts["hidden_steps"] += int(hid.sum())
        if self.safety != "none":
            self.counts["safety_capped"] += int((capped & hid).sum())
        self._leave_record(capped & replay)

    def _leave_record(self, mask: np.ndarray) -> None:
        self.counts["replay_off_record"] += int((mask & ~self.off_record).sum())
        self.off_record |= mask

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

    def _follow_records(
        self, replay: np.ndarray, lane: np.ndarray, arc_m: np.ndarray
    ) -> dict[tuple, str]:
        """Put observed vehicles where the record says (a recorded lane change, or drift),
        if that place is safe now; returns {scene: error} where SUMO refused.

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
        fix_all = (on_record & ((lane != self.lane) | (np.abs(off) > POSITION_TOL_M))) | behind
        errors: dict[tuple, str] = {}
        if not fix_all.any():
            return errors
        eps = np.asarray(self.episode)
        for row in np.ndindex(fix_all.shape[:-1]):
            fix = np.flatnonzero(fix_all[row])
            if not fix.size:
                continue
            act = np.flatnonzero(self.active[row])
            ok = safe_places(
                sec,
                self.lane[row][act],
                self.arc[row][act],
                self.speed[row][act],
                self.bank.length_m[eps[row], act],
                np.searchsorted(act, fix),
                lane[row][fix].astype(np.int64),
                want_arc[row][fix],
                self.dt,
                self.a_min,
                self.sc.bounds.min_gap_m,
            )
            self.counts["replay_moves_refused"] += int((~ok).sum())
            refused = np.zeros(fix_all.shape, dtype=bool)
            refused[(*row, fix[~ok])] = True
            self._leave_record(refused)
            fix = fix[ok]
            if not fix.size:
                continue
            places = [sec.to_lane(int(lane[row][i]), float(want_arc[row][i])) for i in fix]
            try:
                self.sim.move_to(
                    self.ids[row][fix].tolist(),
                    [f"{self._edge_ids[row][e]}_{k}" for e, k, _ in places],
                    [p for _, _, p in places],
                    [self._route_ids[row][e] for e, _, _ in places],
                )
            except Exception as exc:  # SUMO refused: the scene's episode is truncated
                errors[row] = f"{type(exc).__name__}: {exc}"
                continue
            for i, (e, k, p) in zip(fix, places, strict=True):
                self.lane[(*row, i)], self.arc[(*row, i)] = k, sec.offsets_m[e] + p
        return errors

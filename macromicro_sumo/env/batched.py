"""Stage II's env core for B scenes at once: one SUMO simulation steps them all.

``SectionCore`` spends most of a step outside SUMO: one scene's Python modelling (leaders,
observation, reward, replay bookkeeping) and SUMO's fixed cost per simulationStep, for 5
vehicles on the paper's ring. ``BatchedSectionCore`` runs B independent scenes in ONE
simulation of B disjoint copies of the network (``sumo/tiling.py``: scene b drives on
copy b, whose IDs carry the prefix ``copy_prefix(b)``): one simulationStep and one bulk
read serve B env steps, and the modelling is numpy over (B, N) arrays. SUMO is still the
physics: every vehicle's speed command, safe-speed cap and position update is SUMO's, as in
``SectionCore``; the copies share no lane, so a scene cannot see another's vehicles. A
scene stepped here follows the same trajectory as in ``SectionCore`` (tested).

Scope: closed one-lane sections without signals or junction-internal lanes (the paper's
ring and any ring of another radius or N); other sections raise a one-line error and stay
with ``SectionCore``.

Action, observation, reward, starting state and episode end are ``SectionCore``'s, per
scene, with arrays of shape (B, ...) and actions given per slot (hidden slots are read).
Resets happen inside a step (gymnasium's next-step autoreset): a scene reset in a step
is inserted during that step's simulationStep while the other scenes move, as
``SectionCore.reset`` inserts with its own step.
"""

from __future__ import annotations

import tempfile
from itertools import repeat
from pathlib import Path

import numpy as np

from macromicro_sumo.env.batched_scene import (
    BatchStep,
    batch_macro_reward,
    check_batchable,
    loop_observations,
)
from macromicro_sumo.env.section import (
    COUNTERS,
    DEFAULT_SAFETY,
    EXACT_MODE,
    POSITION_TOL_M,
    SAFE_MODE,
    SAFETY,
    SPEED_TOL_MPS,
    SectionCore,
)
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
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.sumo.tiling import copy_id, tile_net


def batched_like(core: SectionCore, n_scenes: int) -> BatchedSectionCore | None:
    """A batched core of ``n_scenes`` scenes that drives ``core``'s episodes as ``core``
    does (its scenario, section, bank, net, seed, safety and vTypes file), or None where
    the section is not one the batched core takes."""
    try:
        check_batchable(core.section)
        opts = core.sim.options
        return BatchedSectionCore(
            core.sc,
            core.section,
            core.bank,
            opts.net_file,
            n_scenes,
            seed=opts.seed,
            safety=core.safety,
            vtypes_file=opts.additional_files[0],
        )
    except UserError:
        return None


class BatchedSectionCore:
    """B scenes of one section in one SUMO run of B network copies (no demand)."""

    def __init__(
        self,
        sc,
        section: Section,
        bank: SectionBank,
        net_file: Path,
        n_scenes: int,
        seed: int = 0,
        safety: str | None = None,
        replay_min_gap_m: float | None = None,
        vclass: str = "passenger",
        vtypes_file: Path | None = None,
    ) -> None:
        safety = safety or getattr(sc.policy, "safety", DEFAULT_SAFETY)
        if safety not in SAFETY:
            raise UserError(f"safety = {safety!r}: one of {', '.join(SAFETY)}")
        if n_scenes < 1:
            raise UserError(f"n_scenes = {n_scenes}: at least 1")
        check_batchable(section)
        self.safety, self.sc, self.section, self.bank = safety, sc, section, bank
        self.counts: dict[str, float] = dict.fromkeys(COUNTERS, 0) | {"replay_lag_m": 0.0}
        self.b, self.n = n_scenes, bank.arc0_m.shape[1]
        self.dt = sc.simulation.step_length_s
        self.a_min, self.a_max = sc.bounds.accel_mps2
        self.observation = sc.policy.observation
        self.obs_dim = len(OBSERVATION_FEATURES[self.observation])
        self._tmp = tempfile.TemporaryDirectory(prefix="macromicro-batched-env-")
        tmp = Path(self._tmp.name)
        lengths = np.concatenate([bank.length_m[bank.valid], bank.true_length_m.ravel()])
        lengths = np.unique(np.round(lengths[np.isfinite(lengths) & (lengths > 0)], 2))
        self._vtype = {float(x): f"mm_L{i}" for i, x in enumerate(lengths)}
        (tmp / "vtypes.add.xml").write_text(
            Path(vtypes_file).read_text()  # a SectionCore's own (``batched_like``)
            if vtypes_file is not None
            else vtypes_xml(
                self._vtype,
                sc.bounds.accel_mps2,
                sc.bounds.min_gap_m,
                vclass,
                self.dt,
                replay_min_gap_m,
            )
        )
        net = tile_net(Path(net_file), n_scenes, tmp / "tiled.net.xml")
        self.sim = Simulation(SumoOptions(net, (tmp / "vtypes.add.xml",), self.dt, seed))
        if self.sim.has_traffic_lights():
            self.close()
            check_batchable(section, True)
        self._add_routes()
        # Every copy's section lanes: ID -> row of (arc of the lane's start, arc per metre).
        lanes = [(copy_id(b, lid), v) for b in range(n_scenes) for lid, v in section.lanes.items()]
        self._lane_code = {lid: k for k, (lid, _) in enumerate(lanes)}
        self._lane_start = np.array([v[2] for _, v in lanes] + [0.0])
        self._lane_scale = np.array([v[3] for _, v in lanes] + [1.0])
        self._resets = np.zeros(n_scenes, dtype=np.int64)
        b, n = n_scenes, self.n
        self.episode = np.zeros(b, dtype=np.int64)
        self.t = np.zeros(b, dtype=np.int64)
        self.done = np.ones(b, dtype=bool)  # no episode yet
        self.ids = np.full((b, n), "", dtype=object)
        self.arc, self.speed = np.zeros((b, n)), np.zeros((b, n))
        self.lane = np.zeros((b, n), dtype=np.int64)
        self.active = np.zeros((b, n), dtype=bool)
        self.hidden = np.zeros((b, n), dtype=bool)
        self.off_record = np.zeros((b, n), dtype=bool)
        self.leader = np.full((b, n), -1, dtype=np.int64)
        self.spacing = np.full((b, n), NO_LEADER_GAP_M)
        self.limits = np.repeat(section.limits_mps[None], b, axis=0)  # (B, E, lanes)
        self._sumo_limits = self.limits.copy()  # what SUMO's lanes have now, per copy
        self._obs = np.zeros((b, n, self.obs_dim))
        self._errors = [""] * b
        self._want = np.zeros((b, n))
        self.valid = np.zeros((b, n), dtype=bool)
        self.rewarded = True

    def _add_routes(self) -> None:
        """Per copy, one route per start edge round the loop, as ``SectionCore`` has."""
        bk, edges = self.bank, list(self.section.edge_ids)
        v = np.nanmax(np.concatenate([bk.speed0_mps[bk.valid], bk.replay_speed_mps.ravel(), [1.0]]))
        reach = (v + self.a_max * bk.horizon * self.dt) * bk.horizon * self.dt
        laps = int(np.ceil(reach / self.section.length_m)) + 2
        for b in range(self.b):
            for e in range(len(edges)):
                route = [copy_id(b, x) for x in (edges[e:] + edges[:e]) * laps]
                self.sim.add_route(self._route(b, e), route)

    @staticmethod
    def _route(b: int, e: int) -> str:
        return f"mm_c{b}_r{e}"

    def close(self) -> None:
        self.sim.close()
        self._tmp.cleanup()

    # ------------------------------------------------------------------ episodes
    def reset(self, episodes: np.ndarray) -> np.ndarray:
        """Start every scene's episode (``episodes``: (B,) bank indices); obs (B, N, d)."""
        return self.step(np.zeros((self.b, self.n)), np.asarray(episodes)).obs

    def _queue(self, scenes: np.ndarray, episodes: np.ndarray) -> None:
        """The old vehicles of ``scenes`` out, their ``episodes``' queued for insertion
        (``SectionCore.reset`` before its step, numpy over the scenes)."""
        bk, sec, n = self.bank, self.section, self.n
        old = self.ids[scenes][self.active[scenes]].tolist()
        was = self.valid[scenes] & ~self.active[scenes]  # a failed insertion may still wait
        if was.any():
            there = set(self.sim.vehicle_ids()) | set(self.sim.pending_vehicles())
            old += [v for v in self.ids[scenes][was] if v in there]
        if old:
            self.sim.remove_vehicles(old)
        lim = self.limits.copy()
        if bk.limits_mps is not None:
            lim[scenes] = bk.limits_mps[episodes]
        now, was_set = lim[scenes], self._sumo_limits[scenes]
        same = (now == was_set) | (np.isnan(now) & np.isnan(was_set))
        for b in scenes[~same.all(axis=(1, 2))]:
            lanes = [
                (copy_id(b, lid), float(lim[b, e, i])) for lid, (e, i, _, _) in sec.lanes.items()
            ]
            self.sim.set_lane_speed_limits([a for a, _ in lanes], [x for _, x in lanes])
            self._sumo_limits[b] = lim[b]
        self.limits = lim
        self._resets[scenes] += 1
        for b in scenes:
            self.ids[b] = [f"c{b}.{self._resets[b]}.{i}" for i in range(n)]
        self.episode[scenes], self.t[scenes] = episodes, 0
        for b in scenes:
            self._errors[b] = ""
        self.hidden[scenes] = bk.hidden[episodes]
        self.valid[scenes] = bk.valid[episodes]
        self.active[scenes] = False
        self.off_record[scenes] = False
        # Sections.to_lane on a one-lane loop, for every slot at once (the same float ops).
        s = np.mod(bk.arc0_m[episodes], sec.length_m)
        e = sec.edge_index(s)
        pos = s - sec.offsets_m[e]
        past = pos > sec.lengths_m[e]
        e = np.where(past, (e + 1) % len(sec.edge_ids), e)
        pos = np.minimum(np.maximum(np.where(past, 0.0, pos), 0.0), sec.lengths_m[e] - 0.01)
        self._want[scenes] = sec.offsets_m[e] + pos  # where SectionCore checks insertion
        hid = self.hidden[scenes]
        sfx = np.where(hid, "" if self.safety == "none" else SAFE_SUFFIX, REPLAY_SUFFIX)
        factor = np.where(sfx == "", 1.0, REPLAY_SPEED_FACTOR)
        rows = scenes[:, None]
        v0 = np.minimum(bk.speed0_mps[episodes], factor * lim[rows, e, 0])
        lengths = np.round(bk.length_m[episodes], 2)
        for j, b in enumerate(scenes):
            for i in np.flatnonzero(self.valid[b]):
                self.sim.add_vehicle(
                    self.ids[b, i],
                    self._route(b, int(e[j, i])),
                    self._vtype[float(lengths[j, i])] + sfx[j, i],
                    0,
                    float(pos[j, i]),
                    float(v0[j, i]),
                )

    def _started(self, scenes: np.ndarray, on: np.ndarray, arc: np.ndarray) -> None:
        """After the insertion step: the insertion check and speed modes of ``scenes``."""
        bk = self.bank
        valid = self.valid[scenes]
        found = valid & on[scenes]
        self.speed[scenes] = np.where(valid, bk.speed0_mps[self.episode[scenes]], 0.0)
        self.lane[scenes] = 0
        self.arc[scenes] = np.where(found, arc[scenes], 0.0)
        self.active[scenes] = found
        off = np.where(found, np.abs(self.arc[scenes] - self._want[scenes]), 0.0).max(axis=1)
        for j, b in enumerate(scenes):
            if (valid[j] & ~found[j]).any():
                miss = int(np.flatnonzero(valid[j] & ~found[j])[0])
                self._errors[b] = f"insertion failed: vehicle {miss} is not on the section"
            elif off[j] > POSITION_TOL_M:
                self._errors[b] = f"insertion check failed: position off by {off[j]:.3f} m"
        hid = valid & self.hidden[scenes]
        obs = valid & ~self.hidden[scenes]
        self.counts["replay_vehicles"] += int(obs.sum())
        ids = self.ids[scenes]
        mode = SAFE_MODE if self.safety == "sumo" else EXACT_MODE
        self.sim.set_speed_mode(ids[hid].tolist(), mode)
        self.sim.set_speed_mode(ids[obs].tolist(), SAFE_MODE)
        self.sim.set_lane_change_mode(ids[obs].tolist(), 0)

    # ------------------------------------------------------------------ step
    def step(self, accel: np.ndarray, reset: np.ndarray | None = None) -> BatchStep:
        """One env step of every running scene; scenes with ``reset[b] >= 0`` start
        episode ``reset[b]`` instead (their ``accel`` row is ignored). ``accel``: (B, N)
        accelerations [m/s^2], read at the hidden slots. A scene past its horizon or
        truncated idles (not stepped) until it is reset."""
        b_n, bk = self.b, self.bank
        rs = np.full(b_n, -1) if reset is None else np.asarray(reset, dtype=np.int64)
        if not self.sim.is_active():  # another simulation took libsumo's one
            if not (rs >= 0).all():
                raise UserError(
                    "another SUMO simulation was started in this process; libsumo runs one "
                    "per process: reset every scene to start this one's again"
                )
            self.sim.reload()  # a fresh run: no routes, no vehicles, the net's limits
            self._add_routes()
            self._sumo_limits = np.repeat(self.section.limits_mps[None], b_n, axis=0)
            self.ids[:], self.active[:], self.valid[:] = "", False, False
        restart = rs >= 0
        run = ~restart & ~self.done
        err = np.array([bool(x) for x in self._errors])
        trunc_now = run & err  # an insertion failure ends the episode at its first step
        run &= ~err
        if restart.any():
            self._queue(np.flatnonzero(restart), rs[restart])
        ep, t = self.episode, np.minimum(self.t, bk.horizon - 1)
        t1 = t + 1
        a = np.minimum(np.maximum(accel, self.a_min), self.a_max)
        hid = self.hidden & run[:, None]
        cmd = np.where(hid, np.maximum(0.0, self.speed + a * self.dt), 0.0)
        obs_slots = self.active & ~self.hidden & run[:, None]
        rv = bk.replay_speed_mps[ep, t1]
        rec_arc, rec_arc0 = bk.replay_arc_m[ep, t1], bk.replay_arc_m[ep, t]
        gone = obs_slots & np.isnan(rv)
        if gone.any():  # the recorded vehicle left the section: it leaves the episode
            self.active &= ~gone
            self.sim.remove_vehicles(list(self.ids[gone]))
        replay = obs_slots & ~gone
        cmd = np.where(replay, rv, cmd)
        back = replay & self.off_record
        if back.any():
            cmd[back] = catch_up_speeds(
                self.speed[back],
                rv[back],
                rec_arc[back],
                self.arc[back],
                arc_lag(self.section, rec_arc0[back], self.arc[back]),
                self.dt,
                (self.a_min, self.a_max),
            )
        live = self.active & run[:, None]
        self.sim.set_speeds(list(self.ids[live]), cmd[live])
        self.sim.step()
        found, arc, read = self._read(
            (restart[:, None] & self.valid) | (run[:, None] & self.active)
        )
        collision = np.zeros(b_n, dtype=bool)
        if self.sim.collisions() > 0:
            for vid in self.sim.colliding_vehicles():
                if vid.startswith("c") and "." in vid:
                    collision[int(vid[1 : vid.index(".")])] = True
        self._count_caps(live, cmd, replay, read)
        lost = live & ~found  # left SUMO (cannot happen on a loop; as SectionCore)
        self.active &= ~lost
        upd = live & ~lost
        self.arc = np.where(upd, arc, self.arc)
        self.speed = np.where(upd, read, self.speed)
        self._rejoin(replay, rec_arc)
        self._follow_records(replay, rec_arc, run)
        self.t[run] += 1
        self._started(np.flatnonzero(restart), found, arc)
        scene = run | restart
        self._scene(scene)
        terms: dict[str, np.ndarray] = {}
        r = np.zeros(b_n)
        if self.rewarded and run.any():
            r, terms = self.macro_reward()
            r = np.where(run, r, 0.0)
        errors = tuple(self._errors)
        emptied = run & ~self.active.any(axis=1)
        truncated = trunc_now | emptied | (run & np.array([bool(x) for x in errors]))
        r = np.where(truncated, 0.0, r)
        self.done = np.where(restart, False, self.done | truncated | (self.t >= bk.horizon))
        return BatchStep(
            self._obs.copy(),
            r,
            terms,
            collision,
            truncated,
            run,
            restart,
            self.active.copy(),
            errors,
        )

    def _read(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(on the section, arc, speed; NaN: not read) of the vehicles in ``slots`` (B, N)."""
        ids = self.ids[slots].tolist()
        try:
            lanes, pos, spd = self.sim.lane_states(ids)
        except KeyError:  # one left SUMO (an open end; not on a loop): read who is there
            st = self.sim.vehicle_states()
            rows = [st.index.get(v, -1) for v in ids]
            lanes = [st.lanes[k] if k >= 0 else "" for k in rows]
            pos = np.array([st.pos_m[k] if k >= 0 else 0.0 for k in rows])
            spd = np.array([st.speed_mps[k] if k >= 0 else np.nan for k in rows])
        # lane ID -> row of the lane tables (-1: no copy's section lane, the tables' last)
        code = np.fromiter(map(self._lane_code.get, lanes, repeat(-1)), np.int64, len(lanes))
        on = np.zeros(slots.shape, dtype=bool)
        on[slots] = code >= 0
        arc = np.zeros(slots.shape)
        speed = np.full(slots.shape, np.nan)
        arc[slots] = self._lane_start[code] + pos * self._lane_scale[code]
        speed[slots] = np.where(code >= 0, spd, np.nan)
        # On a lane of no section copy: gone, and removed, as SectionCore has it.
        stray = [v for v, x, c in zip(ids, lanes, code, strict=True) if x and c < 0]
        if stray:
            self.sim.remove_vehicles(stray)
        return on, arc, speed

    def _count_caps(self, live, cmd, replay, read) -> None:
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

    def _rejoin(self, replay: np.ndarray, rec_arc: np.ndarray) -> None:
        off = replay & self.active & self.off_record
        if not off.any():
            return
        lag = np.abs(arc_lag(self.section, rec_arc, self.arc))
        back = off & (lag <= POSITION_TOL_M)
        self.off_record &= ~back
        self.counts["replay_returned"] += int(back.sum())
        still = off & ~back
        self.counts["replay_off_steps"] += int(still.sum())
        self.counts["replay_lag_m"] += float(lag[still].sum())

    def _follow_records(self, replay: np.ndarray, rec_arc: np.ndarray, run: np.ndarray) -> None:
        """``SectionCore._follow_records`` on one lane: an on-record vehicle drifted more
        than ``POSITION_TOL_M`` from its record is put back where that is safe (rare: a
        scene loop only where one drifted)."""
        sec = self.section
        on_record = replay & self.active & ~self.off_record
        off = np.mod(self.arc - rec_arc + sec.length_m / 2, sec.length_m) - sec.length_m / 2
        fix_all = on_record & (np.abs(off) > POSITION_TOL_M)
        for b in np.flatnonzero(fix_all.any(axis=1)):
            fix = np.flatnonzero(fix_all[b])
            act = np.flatnonzero(self.active[b])
            ok = safe_places(
                sec,
                self.lane[b, act],
                self.arc[b, act],
                self.speed[b, act],
                self.bank.length_m[self.episode[b], act],
                np.searchsorted(act, fix),
                np.zeros(fix.size, dtype=np.int64),
                rec_arc[b, fix],
                self.dt,
                self.a_min,
                self.sc.bounds.min_gap_m,
            )
            self.counts["replay_moves_refused"] += int((~ok).sum())
            refused = np.zeros((self.b, self.n), dtype=bool)
            refused[b, fix[~ok]] = True
            self._leave_record(refused)
            fix = fix[ok]
            if not fix.size:
                continue
            places = [sec.to_lane(0, float(rec_arc[b, i])) for i in fix]
            try:
                self.sim.move_to(
                    list(self.ids[b, fix]),
                    [f"{copy_id(b, sec.edge_ids[e])}_{k}" for e, k, _ in places],
                    [p for _, _, p in places],
                    [self._route(b, e) for e, _, _ in places],
                )
            except Exception as exc:  # SUMO refused: this scene's episode is truncated
                self._errors[b] = f"{type(exc).__name__}: {exc}"
                continue
            for i, (e, _k, p) in zip(fix, places, strict=True):
                self.arc[b, i] = sec.offsets_m[e] + p

    # ------------------------------------------------------------------ scene
    def _scene(self, scenes: np.ndarray) -> None:
        """Leaders, spacings and observations of ``scenes`` (the others keep theirs)."""
        f = self.bank.driver_factor
        obs, leader, spacing = loop_observations(
            self.section,
            self.limits,
            self.arc,
            self.speed,
            self.active & scenes[:, None],
            self.obs_dim,
            None if f is None else f[self.episode],
        )
        keep = ~scenes[:, None]
        self.leader = np.where(keep, self.leader, leader)
        self.spacing = np.where(keep, self.spacing, spacing)
        self._obs = np.where(keep[..., None], self._obs, obs)

    def observations(self) -> np.ndarray:
        return self._obs.copy()

    def macro_reward(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """r_macro (B,) and its named terms of every scene (``section_macro_reward``)."""
        g = self.sc.generator
        return batch_macro_reward(
            self.speed,
            self.spacing,
            self.leader,
            self.hidden,
            self.active,
            self.bank.psi[self.episode],
            g.lambda_v,
            g.lambda_d,
            self.sc.policy.macro_speed_scale_mps,
        )

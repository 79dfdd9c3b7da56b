"""Stage II's env core for B scenes at once: one SUMO simulation steps them all.

``SectionCore`` spends most of a step outside SUMO: one scene's Python modelling (leaders,
observation, reward, replay bookkeeping) and SUMO's fixed cost per simulationStep, for 5
vehicles on the paper's ring. ``BatchedSectionCore`` runs B independent scenes in ONE
simulation of B disjoint copies of the network (``sumo/tiling.py``: scene b drives on
copy b, whose IDs carry the prefix ``copy_prefix(b)``): one simulationStep and one bulk
read serve B env steps, and the modelling is numpy over (B, N) arrays. SUMO is still the
physics: every vehicle's speed command, safe-speed cap and position update is SUMO's, as in
``SectionCore``; the copies share no lane, so a scene cannot see another's vehicles. The
step itself (commands, SUMO's step and read-back, the replay's bookkeeping) is the one both
cores run (``env/slot_core.py``), over (B, N) here; what is this core's own is the
insertion of B scenes at once and the loop's leaders, observations and reward
(``env/batched_scene.py``). A scene stepped here follows the same trajectory as in
``SectionCore``, to the bit (tested).

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

from functools import partial
from pathlib import Path

import numpy as np

from macromicro_sumo.env.batched_scene import (
    BatchStep,
    batch_macro_reward,
    check_batchable,
    loop_observations,
)
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.env.slot_core import POSITION_TOL_M, SlotCore
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.leaders import set_leader_gap
from macromicro_sumo.road.physics import observes_gap, set_own_features
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.sumo.states import DEFAULT_LANE_CHANGE_MODE
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


class BatchedSectionCore(SlotCore):
    """B scenes of one section in one SUMO run of B network copies (no demand)."""

    _reward_fn = staticmethod(batch_macro_reward)  # ``SlotCore.macro_reward``, per row

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
        vtypes_file: Path | None = None,  # a SectionCore's own (``batched_like``)
        reuse_vehicles: bool = True,  # reset by placing the vehicles there (``_queue``)
    ) -> None:
        if n_scenes < 1:
            raise UserError(f"n_scenes = {n_scenes}: at least 1")
        check_batchable(section)
        vtypes = self._setup(sc, bank, safety, vclass, replay_min_gap_m, vtypes_file)
        self.section, self.b = section, n_scenes
        net = tile_net(Path(net_file), n_scenes, vtypes.parent / "tiled.net.xml")
        self.sim = Simulation(SumoOptions(net, (vtypes,), self.dt, seed))
        if self.sim.has_traffic_lights():
            self.close()
            check_batchable(section, True)
        copies = range(n_scenes)
        self._add_routes(
            np.array([[copy_id(b, e) for e in section.edge_ids] for b in copies], object)
        )
        self._index_lanes([partial(copy_id, b) for b in copies])
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
        # Vehicles of reset scenes placed after the step: (IDs, vTypes, lanes, positions,
        # routes, speeds, detour lanes), ``Simulation.place_vehicles``' arguments.
        self._moves: tuple[list, ...] = ()
        self.reuse_vehicles = reuse_vehicles

    # ------------------------------------------------------------------ episodes
    def reset(self, episodes: np.ndarray) -> np.ndarray:
        """Start every scene's episode (``episodes``: (B,) bank indices); obs (B, N, d)."""
        return self.step(np.zeros((self.b, self.n)), np.asarray(episodes)).obs

    def _queue(self, scenes: np.ndarray, episodes: np.ndarray) -> None:
        """The old vehicles of ``scenes`` out, their ``episodes``' queued for insertion
        (``SectionCore.reset`` before its step, numpy over the scenes).

        With ``reuse_vehicles``, a vehicle on the road whose slot the new episode fills
        stays, and is placed after the step (``Simulation.place_vehicles``: its vType,
        lane, position, route and speed as a fresh insertion has them): vehicle.add was
        most of a reset. The same trajectories to the bit (tests/env/test_batched.py).
        """
        bk, sec, n = self.bank, self.section, self.n
        keep = self.active[scenes] & bk.valid[episodes] & self.reuse_vehicles
        old = self.ids[scenes][self.active[scenes] & ~keep].tolist()
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
        kept_ids, was_hidden = self.ids[scenes], self.hidden[scenes]
        for b in scenes:
            self.ids[b] = [f"c{b}.{self._resets[b]}.{i}" for i in range(n)]
        self.ids[scenes] = np.where(keep, kept_ids, self.ids[scenes])
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
        sfx, factor = self._insert_kinds(self.hidden[scenes])
        rows = scenes[:, None]
        v0 = np.minimum(bk.speed0_mps[episodes], factor * lim[rows, e, 0])
        lengths = np.round(bk.length_m[episodes], 2)
        # Each slot's vType ("": an empty slot's, whose length is no vehicle's).
        vtypes = np.vectorize(lambda x: self._vtype.get(float(x), ""), otypes=[object])(lengths)
        vtypes = vtypes + sfx
        if keep.any():
            rows, e_next = np.broadcast_to(rows, keep.shape), (e + 1) % len(sec.edge_ids)
            self._moves = (
                self.ids[scenes][keep].tolist(),
                vtypes[keep].tolist(),
                [f"{x}_0" for x in self._edge_ids[rows[keep], e[keep]]],
                pos[keep].tolist(),
                self._route_ids[rows[keep], e[keep]].tolist(),
                v0[keep].tolist(),
                [f"{x}_0" for x in self._edge_ids[rows[keep], e_next[keep]]],
            )
            # A hidden vehicle that was observed gets SUMO's default lane changing back
            # (observed ones have none: ``_set_modes``).
            back = self.ids[scenes][keep & self.hidden[scenes] & ~was_hidden].tolist()
            self.sim.set_lane_change_mode(back, DEFAULT_LANE_CHANGE_MODE)
        for j, b in enumerate(scenes):
            for i in np.flatnonzero(self.valid[b] & ~keep[j]):
                self.sim.add_vehicle(
                    self.ids[b, i],
                    self._route_ids[b, e[j, i]],
                    vtypes[j, i],
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
        slots = np.zeros((self.b, self.n), dtype=bool)
        slots[scenes] = valid
        self._set_modes(slots)

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
            self._add_routes(self._edge_ids)
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
        cmd, replay, live = self._drive(accel, run[:, None], ep, t)
        if self._moves:  # reset scenes' vehicles, where the insertion step leaves new ones
            self.sim.place_vehicles(*self._moves)
            self._moves = ()
        state = self._read((restart[:, None] & self.valid) | (run[:, None] & self.active))
        collision = np.zeros(b_n, dtype=bool)
        if self.sim.collisions() > 0:
            for vid in self.sim.colliding_vehicles():
                if vid.startswith("c") and "." in vid:
                    collision[int(vid[1 : vid.index(".")])] = True
        collision &= ~restart  # a reset scene's old vehicles still drove in this step
        for (b,), msg in self._after(live, cmd, replay, state, ep, t).items():
            self._errors[b] = msg  # SUMO refused a recorded move: the episode is truncated
        self.t[run] += 1
        self._started(np.flatnonzero(restart), state[0], state[2])
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

    # ------------------------------------------------------------------ scene
    def _scene(self, scenes: np.ndarray) -> None:
        """Leaders, spacings and observations of ``scenes`` (the others keep theirs)."""
        f = self.bank.driver_factor
        live = self.active & scenes[:, None]
        obs, leader, spacing = loop_observations(
            self.section,
            self.limits,
            self.arc,
            self.speed,
            live,
            self.obs_dim,
            None if f is None else f[self.episode],
        )
        lengths = np.where(live, self.bank.length_m[self.episode], 0.0)
        set_own_features(obs, self.observation, lengths)
        if observes_gap(self.observation):  # the leader's own length (inactive: 0 stays 0)
            lead = np.take_along_axis(lengths, np.maximum(leader, 0), axis=1)
            set_leader_gap(obs, self.observation, np.where(live, lead, 0.0))
        keep = ~scenes[:, None]
        self.leader = np.where(keep, self.leader, leader)
        self.spacing = np.where(keep, self.spacing, spacing)
        self._obs = np.where(keep[..., None], self._obs, obs)

    @property
    def _target(self) -> np.ndarray:
        """Each scene's psi (B, fields): what its reward compares with."""
        return self.bank.psi[self.episode]

"""Stage II's "demand" episodes on a section: a window of a training run replayed from the
scenario's own demand, the hidden population driven by the policy as it enters.

Snapshot episodes (``env.section``) start from a generated completion and last H steps
(5 s): no vehicle enters, and a policy trained on them alone never meets the closing
speeds, dense platoons and merges a deployment (``deploy``) meets over whole runs. A demand
episode is what a deployment does, on a training run of the ground truth:

* SUMO runs the run's demand with the ground truth's seed (``sc.seed + run``) and drives
  every vehicle until the window starts (``t0``); a ``[fleet]`` scenario's demand is its
  fleet, inserted exactly as the truth inserted it (the run's draws, SUMO seed and speed
  limits, ``truth.fleet``) and checked after SUMO's first step, which every window then
  follows (t0 >= one step); from then on every vehicle of the
  population (not instrumented, ``truth.section.is_instrumented``) is driven by the policy
  from the step it is on a lane of the section until it leaves it, instrumented vehicles
  keep their own SUMO models (as in a deployment);
* speed commands v' = max(0, v + a dt), a at most the vType's accel and v' at most its
  maxSpeed (``road.vtype.command_speeds``, the deployment's rule), apply exactly (speed
  mode 32, the deployment's ``safety = "none"``): the policy meets the consequences of its
  own actions;
* observations are the deployment's, from SUMO's state (``sumo_observations``: SUMO's
  leader along the lane connections, a red light or the end of a lane the vehicle must
  leave as a standing leader) with the section env's lookahead (``env.section_bank``),
  at the run's speed limits (``data.section.run_section``);
  tests check both against the env's observation of the same state;
* with ``policy.driver_speed`` (``set_driver_speeds``), each driven vehicle observes the
  limits times its own desired-speed factor, as a deployment's driver
  (``env.driver_speed.DriverSpeeds`` of the run: "drawn" by (seed, run, vehicle),
  "memory" from its speed where it entered the section, before the window for a vehicle
  already there), so that the policy meets here the drivers the snapshot episodes and the
  deployment give it;
* with ``policy.driver_follow`` (``set_driver_taus``), each driven vehicle observes its own
  tau as a trailing column (``env.driver_tau.DriverTaus`` of the run, the deployment's);
* the reward of a step is the section env's r_macro of every vehicle on the section
  against psi of the detector interval holding the step (``section_macro_reward``);
* a vehicle whose front passed its leader's back (a collision) is removed: its episode
  ends there (``DemandStep.collided``); one that leaves the section ends without a
  terminal (``DemandStep.left``);
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from macromicro_sumo.data.section import PSI_FIELDS, SectionTruth, psi_table, run_section
from macromicro_sumo.env.driver_speed import DriverSpeeds
from macromicro_sumo.env.driver_tau import DriverTaus, with_tau
from macromicro_sumo.env.observed_drivers import scale_limits
from macromicro_sumo.env.section_bank import section_macro_reward, section_target
from macromicro_sumo.road.leaders import nearer_standing, set_leader_gap, stop_distance_m
from macromicro_sumo.road.physics import (
    LIMIT_COLUMN,
    OBSERVATION_FEATURES,
    has_lookahead,
    set_own_features,
)
from macromicro_sumo.road.section import NO_LEADER_GAP_M, Section
from macromicro_sumo.road.vtype import VTypePhysics, accel_limit, command_speeds, read_vtype
from macromicro_sumo.scenario.fleet import fleet_demand
from macromicro_sumo.sumo.fleet import FLEET_ROUTE_PREFIX
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth import fleet
from macromicro_sumo.truth.section import fleet_specs, is_instrumented
from macromicro_sumo.truth.section_detectors import without_detectors

EXACT_MODE = 32  # speed commands applied exactly (the deployment's safety = "none")
STOP_DECEL_MPS2 = 9.0  # a standing "leader" (stop line, lane end) never brakes


@dataclass
class DemandStep:
    """What one step of a demand episode returns."""

    r_macro: float
    collided: list[str]  # driven vehicles whose episode ended in a collision this step
    left: list[str]  # driven vehicles that left the section (or the network) this step
    collisions: int  # every vehicle that collided (driven or not)


# --------------------------------------------------------------------------- observations


@dataclass
class SumoScene:
    """Observations of driven vehicles from SUMO's state, with what the reward needs."""

    obs: np.ndarray  # (V, obs_dim)
    leader: list[str]  # SUMO's leader ("" none or a standing obstacle)
    spacing_m: np.ndarray  # (V,) front-to-front spacing to ``leader`` (NO_LEADER_GAP_M: none)
    gap_m: np.ndarray  # (V,) SUMO's gap to what the vehicle sees ahead


def lane_places(
    section: Section, vids: list[str], states: dict[str, tuple[str, float, float, float]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per vehicle of ``vids`` (on the section's lanes; ``states``: SUMO's lane states) its
    lane index, arc [m], edge index and its lane's speed limit there [m/s]."""
    n = len(vids)
    lane = np.empty(n, dtype=np.int64)
    arc = np.empty(n)
    for i, v in enumerate(vids):
        _e, idx, start, scale = section.lanes[states[v][0]]
        lane[i], arc[i] = idx, start + states[v][1] * scale
    edge = section.edge_index(arc)
    return lane, arc, edge, section.limits_mps[edge, np.minimum(lane, section.n_lanes[edge] - 1)]


def sumo_observations(
    observation: str,
    section: Section,
    vids: list[str],
    states: dict[str, tuple[str, float, float, float]],
    leaders: dict[str, tuple[str, float]],
    shapes: dict[str, tuple[float, float, float]],
    stops_m: np.ndarray,
) -> SumoScene:
    """Observations (V, obs_dim) of ``vids`` as a deployment builds them from SUMO.

    ``states``: SUMO's lane states, ``leaders``: SUMO's leader and gap (leader's back minus
    own front and minGap), ``shapes``: each vehicle's (length, minGap, decel),
    ``stops_m``: (V,) SUMO's gap to a stop at a red light or the end of a lane the vehicle
    must leave (``road.leaders.stop_distance_m``; inf: none), a standing leader there
    (``road.leaders.nearer_standing``). Spacing is
    front to front: gap + own minGap + leader's length, as the env's arcs give it (a gap
    layout observes it less the leader's length, ``road.leaders.set_leader_gap``).
    """
    n = len(vids)
    speed = np.array([states[v][2] for v in vids])
    lane, arc, edge, limit = lane_places(section, vids, states)
    spacing = np.full(n, NO_LEADER_GAP_M)
    gap_out = np.full(n, NO_LEADER_GAP_M)
    own_length = np.array([shapes[v][0] for v in vids], dtype=float)
    lead_length = own_length.copy()  # a standing leader's (the gap layouts' leader column)
    lead_v = speed.copy()  # delta_v 0 without a leader
    leader = [""] * n
    min_gap = np.array([shapes[v][1] for v in vids], dtype=float)
    for i, v in enumerate(vids):
        lid, gap = leaders.get(v, ("", -1.0))
        if lid and lid in states and lid in shapes:
            s = gap + min_gap[i] + shapes[lid][0]
            if s < NO_LEADER_GAP_M:
                spacing[i], lead_v[i], gap_out[i], leader[i] = s, states[lid][2], gap, lid
                lead_length[i] = shapes[lid][0]
    # A red light, or the end of a lane the vehicle must leave: a standing leader there.
    stops = np.asarray(stops_m, dtype=float)
    closer = nearer_standing(spacing, stops, own_length, min_gap)
    lead_length[closer] = own_length[closer]
    lead_v[closer] = 0.0
    gap_out[closer] = np.maximum(stops[closer], 0.0)  # SUMO's gap to its stop, as deployed
    for i in np.flatnonzero(closer).tolist():
        leader[i] = ""
    cols = [speed, limit, spacing, speed - lead_v]
    if has_lookahead(observation):
        cols += list(section.lookahead(lane, arc, edge, limit))
    obs = np.zeros((n, len(OBSERVATION_FEATURES[observation])))
    if n:
        obs[:, : len(cols)] = np.stack(cols, axis=1)
    set_own_features(obs, observation, own_length)
    set_leader_gap(obs, observation, lead_length)  # a gap layout: the bumper gap
    return SumoScene(obs, leader, spacing, gap_out)


# --------------------------------------------------------------------------- the core


class DemandCore:
    """Demand episodes of the training runs ``runs`` of a section scenario's ground truth.

    ``reset(run, t0_s)`` starts the run's demand (SUMO drives until ``t0_s``);
    ``observe()`` returns the driven vehicles and their observations, ``step(accel)``
    drives them one step. One SUMO simulation, reloaded for each episode (libsumo holds one
    per process: a snapshot env in the same process takes it over and gives it back).
    """

    def __init__(self, sc, truth: SectionTruth, runs: np.ndarray, horizon_steps: int) -> None:
        self.sc = sc
        self.truth = truth
        self.section = truth.section  # with the episode's run's limits from reset() on
        # A [fleet] scenario: the ring and every run's draws, as the truth drew them.
        self._fleet = fleet_specs(sc, truth.section) if fleet_demand(sc) is not None else None
        self.runs = np.asarray(runs, dtype=np.int64)
        self.horizon = int(horizon_steps)
        self.dt = sc.simulation.step_length_s
        self.observation = sc.policy.observation
        self.obs_dim = len(OBSERVATION_FEATURES[self.observation])
        inputs = scenario_inputs(sc)
        self._tmp = tempfile.TemporaryDirectory(prefix="macromicro-demand-")
        adds = tuple(
            without_detectors(p, Path(self._tmp.name) / f"user_{i}_{p.name}")
            for i, p in enumerate(inputs.additional_files)
        )
        self._inputs, self._adds = inputs, adds
        psi = psi_table(truth, sc)
        psi = psi[np.isfinite(psi["mean_speed_mps"])]
        self._psi = {
            int(r): (
                g["begin_s"].to_numpy(dtype=float),
                g["end_s"].to_numpy(dtype=float),
                g[list(PSI_FIELDS)].to_numpy(dtype=float),
            )
            for r, g in psi.groupby("run")
        }
        self.sim: Simulation | None = None
        self.run, self.t = -1, 0
        self.types: dict[str, str] = {}  # vehicle -> its vType
        self.vtypes: dict[str, VTypePhysics] = {}  # vType -> its record, read once
        # The maxSpeed [m/s] and accel [m/s^2] of the vehicles driven now (``observe``): a
        # step's cap is one array op.
        self._vmax_driven: np.ndarray = np.zeros(0)
        self._accel_driven: np.ndarray = np.zeros(0)
        self.population: set[str] = set()
        self.driven: list[str] = []
        self._speed: np.ndarray = np.zeros(0)
        self._has_lights = False
        # policy.driver_speed: the drivers' factor quantiles (``set_driver_speeds``) and
        # this episode's drivers (None: every driver the limits as they are).
        self._driver_quantiles: np.ndarray | None = None
        self.drivers: DriverSpeeds | None = None
        # policy.driver_follow: the drivers' tau quantiles, the Krauss prior that hands a
        # tau over (None: the draw from the first step) and this episode's taus.
        self._tau_quantiles: np.ndarray | None = None
        self._tau_prior: Mapping[str, float] | None = None
        self.taus: DriverTaus | None = None
        self.counts = {"episodes": 0, "vehicle_steps": 0, "collisions": 0, "teleports": 0}

    # ------------------------------------------------------------------ episodes
    def set_driver_speeds(self, quantiles: np.ndarray | None) -> None:
        """``policy.driver_speed`` (not "none"): from the next ``reset`` on, each driven
        vehicle observes the limits times its own factor from the drivers' ratio
        ``quantiles`` (the agent's ``driver_speed`` buffer, as a deployment's
        ``DriverSpeeds`` takes them); None: the limits as they are."""
        off = quantiles is None or self.sc.policy.driver_speed == "none"
        self._driver_quantiles = None if off else np.asarray(quantiles, dtype=float)

    def set_driver_taus(
        self, quantiles: np.ndarray | None, prior: Mapping[str, float] | None = None
    ) -> None:
        """``policy.driver_follow``: from the next ``reset`` on, each driven vehicle's
        observation ends in its own tau from the drivers' tau ``quantiles`` (the agent's
        ``driver_tau`` buffer, as the deployment's ``DriverTaus``); None: no column.
        ``prior``: the Krauss prior's parameters by name, with which a driver's tau is
        handed over from the one its first observed gap supports, as in the deployment
        (``DriverTaus``, ``deploy.policy_batch``)."""
        self._tau_quantiles = None if quantiles is None else np.asarray(quantiles, dtype=float)
        self._tau_prior = prior
        self.obs_dim = len(OBSERVATION_FEATURES[self.observation]) + (quantiles is not None)

    def windows(self, rng: np.random.Generator, n: int) -> list[tuple[int, float]]:
        """``n`` episode starts (run, t0): a run with psi, a start on the step grid such
        that the window lies after the warm-up and inside the recorded duration."""
        runs = [int(r) for r in self.runs if int(r) in self._psi]
        sim = self.sc.simulation
        lo = sim.warmup_s if self._fleet is None else max(sim.warmup_s, self.dt)  # inserted
        hi = max(lo, sim.warmup_s + sim.duration_s - self.horizon * self.dt)
        out = []
        for _ in range(n):
            r = runs[int(rng.integers(len(runs)))]
            t0 = lo + float(rng.uniform(0.0, hi - lo))
            out.append((r, round(round(t0 / self.dt) * self.dt, 6)))
        return out

    def reset(self, run: int, t0_s: float) -> None:
        """Start ``run``'s demand and let SUMO drive everyone until ``t0_s`` (a fleet: at
        least its insertion step)."""
        seed, adds, fleet_run = self.sc.seed + int(run), self._adds, None
        if self._fleet is not None:  # the truth's files, seed and exact insertion
            geo, specs = self._fleet
            fleet_run = (specs[int(run)], geo)
            seed = fleet_run[0].sumo_seed
            folder = Path(self._tmp.name) / f"run_{int(run):03d}"
            folder.mkdir(exist_ok=True)
            span_s = self.sc.simulation.warmup_s + self.sc.simulation.duration_s
            demand = fleet_demand(self.sc)
            adds += fleet.write_fleet_inputs(folder, fleet_run[0], geo, demand, self.dt, span_s)
        opts = SumoOptions(
            self._inputs.net_file,
            adds,
            self.dt,
            seed,
            route_files=self._inputs.route_files,
            user_demand=fleet_run is None,
        )
        if self.sim is None:
            self.sim = Simulation(opts)
        else:
            self.sim.options = opts
            self.sim.reload()
        sim = self.sim
        self.run, self.t = int(run), 0
        self.section = run_section(self.truth, self.run)
        self.types, self.population, self.driven = {}, set(), []
        q = self._driver_quantiles
        self.drivers = None if q is None else DriverSpeeds(q, self.sc, self.run)
        q = self._tau_quantiles
        self.taus = None if q is None else DriverTaus(q, self.sc, self.run, self._tau_prior)
        steps = int(round(t0_s / self.dt))
        if fleet_run is not None:
            fleet.insert_fleet(sim, *fleet_run, FLEET_ROUTE_PREFIX)
            sim.step()
            fleet.check_fleet_inserted(sim, *fleet_run)
            steps -= 1
        # "memory": each driver's factor from its speed where it entered the section, as a
        # deployment's driver sets it, not where the window finds it (before: on
        # netgen_corridor the vehicles on the section at t0 took 0.91 on average where
        # their entries gave 1.02, and 56% more than 0.05 lower)
        memory = self.drivers is not None and self.drivers.kind == "memory"
        if memory and fleet_run is not None:  # on the road since its first step
            self._remember_entries()
        for _ in range(steps):
            sim.step()
            if memory:
                self._remember_entries()
        self._arrive([v for v in sim.vehicle_ids() if v not in self.types])
        self._has_lights = sim.has_traffic_lights()
        self.counts["episodes"] += 1

    def _remember_entries(self) -> None:
        """``DriverSpeeds`` of the population vehicles on the section now that it has not
        met yet: their factors from their observations here, as a deployed driver's first
        sight (SUMO drives them before the window as it drives them into a deployment's
        section). With ``policy.driver_entry`` "queued" the speed and limit columns alone
        (``sight_factors`` reads no more): no leaders or stops asked of SUMO."""
        self._arrive([v for v in self.sim.vehicle_ids() if v not in self.types])
        states = self.lane_states()
        lanes, known = self.section.lanes, self.drivers.factor
        new = [
            v for v in states if v in self.population and v not in known and states[v][0] in lanes
        ]
        if new and self.drivers.entry == "queued":  # reads the speed and limit alone
            sight = np.zeros((len(new), LIMIT_COLUMN + 1))  # an observation's first columns
            sight[:, 0] = [states[v][2] for v in new]
            sight[:, LIMIT_COLUMN] = lane_places(self.section, new, states)[3]
            self.drivers(new, sight)
        elif new:  # their observations, as the deployment's first sight (what is ahead)
            shapes = {v: self.vtypes[self.types[v]].shape for v in states if v in self.types}
            leaders, stops = self.sim.read_leaders(), self._stops(new, states)
            scene = sumo_observations(
                self.observation, self.section, new, states, leaders, shapes, stops
            )
            self.drivers(new, scene.obs)

    def _arrive(self, vids) -> None:
        sim = self.sim
        if not vids:
            return
        sim.subscribe_driving(vids, NO_LEADER_GAP_M)
        for vid in vids:
            vt = sim.vehicle_type(vid)
            self.types[vid] = vt
            if vt not in self.vtypes:
                self.vtypes[vt] = read_vtype(sim, vt)
            if not is_instrumented(self.sc, vid, vt, self.run):
                self.population.add(vid)

    def time_s(self) -> float:
        return self.sim.time_s()

    def _stops(self, vids: list[str], states) -> np.ndarray:
        sim = self.sim
        stops = np.array([sim.lane_end_m(v, states[v][0], states[v][1]) for v in vids])
        if self._has_lights and len(vids):
            gaps = [self.vtypes[self.types[v]].stopline_gap_m for v in vids]
            stops = stop_distance_m(stops, sim.stop_lines_m(vids), np.array(gaps))  # NaN: none
        return stops

    def lane_states(self) -> dict[str, tuple[str, float, float, float]]:
        """SUMO's lane states of the vehicles in the network now: after a reload,
        subscription results of the last run's vehicles can linger."""
        ids = set(self.sim.vehicle_ids())
        return {v: s for v, s in self.sim.read_lane_states().items() if v in ids}

    def observe(self) -> tuple[list[str], np.ndarray]:
        """The driven vehicles now (sorted) and their observations (V, obs_dim)."""
        sim = self.sim
        states = self.lane_states()
        lanes = self.section.lanes
        now = sorted(v for v in self.population if v in states and states[v][0] in lanes)
        fresh = sorted(set(now) - set(self.driven))
        if fresh:
            sim.set_speed_mode(fresh, EXACT_MODE)
        gone = [v for v in self.driven if v not in now and v in states]
        if gone:
            sim.release_speeds(gone)
        self.driven = now
        phys = [self.vtypes[self.types[v]] for v in now]
        self._vmax_driven = np.array([p.max_speed_mps for p in phys])
        self._accel_driven = np.array([p.accel_mps2 for p in phys])
        shapes = {v: self.vtypes[self.types[v]].shape for v in states if v in self.types}
        scene = sumo_observations(
            self.observation,
            self.section,
            now,
            states,
            sim.read_leaders(),
            shapes,
            self._stops(now, states),
        )
        self._speed = scene.obs[:, 0].copy() if len(now) else np.zeros(0)
        if self.drivers is not None and now:  # each driver's own limits (DriverSpeeds)
            scale_limits(scene.obs, self.drivers(now, scene.obs))
        if self.taus is not None:  # policy.driver_follow: each driver's own tau, last
            return now, with_tau(scene.obs, self.taus(now, scene.obs, self.t))
        return now, scene.obs

    def step(self, accel: np.ndarray) -> DemandStep:
        """Apply ``accel`` (one per vehicle of the last ``observe``) and step SUMO."""
        sim = self.sim
        a_min, a_max = self.sc.bounds.accel_mps2
        driven = self.driven
        if driven:
            # At most the vType's maxSpeed and accel, its physics, by the deployment's rule
            # (``road.vtype``): speed mode 32 would apply a command beyond either.
            a_max = accel_limit(a_max, self._accel_driven)
            cmd = command_speeds(self._speed, accel, self.dt, a_min, a_max, self._vmax_driven)
            sim.set_speeds(driven, cmd)
        sim.step()
        self.t += 1
        self._arrive(sim.departed())
        collisions = sim.collisions()
        self.counts["collisions"] += collisions
        self.counts["teleports"] += sim.teleports()
        self.counts["vehicle_steps"] += len(driven)
        states = self.lane_states()
        leaders = sim.read_leaders()
        lanes = self.section.lanes
        on = [v for v in states if states[v][0] in lanes and v in self.types]
        # A collision: the follower's front passed the leader's back (SUMO's gap is net of
        # the follower's minGap). The follower is removed, as SUMO's collision.action
        # "remove" would, so the run goes on without a stuck pair.
        hit = []
        for v in on:
            lid, gap = leaders.get(v, ("", -1.0))
            if lid and gap + self.vtypes[self.types[v]].min_gap_m < 0.0:
                hit.append(v)
        if hit:
            sim.remove_vehicles(hit)
            hit_set = set(hit)
            on = [v for v in on if v not in hit_set]
        r = self._reward(on, states, leaders)
        now = set(on)
        left = [v for v in driven if v not in now and v not in hit]
        return DemandStep(r, [v for v in hit if v in set(driven)], left, collisions)

    def _reward(self, on: list[str], states, leaders) -> float:
        """r_macro of every vehicle on the section against psi of the interval now."""
        if not on:
            return 0.0
        begin, end, psi = self._psi[self.run]
        t = self.sim.time_s()
        k = np.flatnonzero((begin <= t) & (end > t))
        if not k.size:
            k = np.array([int(np.argmin(np.abs(begin - t)))])
        index = {v: i for i, v in enumerate(on)}
        speed = np.array([states[v][2] for v in on])
        leader = np.full(len(on), -1, dtype=np.int64)
        spacing = np.full(len(on), NO_LEADER_GAP_M)
        for i, v in enumerate(on):
            lid, gap = leaders.get(v, ("", -1.0))
            j = index.get(lid, -1) if lid else -1
            if j >= 0:
                own, ahead = self.vtypes[self.types[v]], self.vtypes[self.types[lid]]
                s = gap + own.min_gap_m + ahead.length_m
                if s < NO_LEADER_GAP_M:
                    leader[i], spacing[i] = j, s
        hidden = np.array([v in self.population for v in on])
        g = self.sc.generator
        r, _ = section_macro_reward(
            speed,
            spacing,
            leader,
            hidden,
            np.ones(len(on), dtype=bool),
            section_target(psi[int(k[0])]),
            g.lambda_v,
            g.lambda_d,
            self.sc.policy.macro_speed_scale_mps,
        )
        return r

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()
        self._tmp.cleanup()

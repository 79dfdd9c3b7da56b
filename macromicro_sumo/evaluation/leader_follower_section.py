"""Leader-follower tests (the paper's Fig. 3) on a section of the user's network.

The ring's tests (``leader_follower``) on any section, through the section's own env core
(``env.section.SectionCore``, the one that trains and evaluates the policy there): two
vehicles on one lane path of the section, the leader replaying the profile (accelerate /
decelerate), the follower driven by each method; the same trials, RMSE and CSV columns
(``leader_follower.run_tests``). What the section adds:

* the lane path (``lane_path``): from the rightmost lane of the first edge that leads on
  to the section's end (round the loop on a closed section) without a lane change, along
  the network's connections; both vehicles keep their lane (SUMO lane-change mode 0);
* the road: one uniform limit on every lane of the section, as the ring's test has it
  (the fleet's upper limit where the scenario has ``[speed_limits]``, else the highest
  limit on the path); the profile scaled to it and to the ground truth's mean spacing
  (``LeaderProfile.moved``); on an open section the follower starts one vehicle length
  from the section's start and the leader must not reach its end within the test;
* both vehicles are hidden ones (speed mode 0, no safety layer): the core's replayed
  vehicles follow their recorded positions, so the leader is commanded the profile's next
  speed instead (``run_trial``); exact to rounding (1e-15 m/s);
* the reference follower (``reference_idm``): the fleet's IDM (the middle of its ranges,
  as the ring) where the scenario has ``[fleet]``; otherwise its vehicles are not IDM and
  the reference is IDM fitted by least squares to every recorded vehicle of the ground
  truth. The ``IDM`` rows of the CSVs are that reference; ``SectionLeaderFollower.reference``
  says which.

Where the test cannot run on the section (too short for the profile, no lane path, a
ramp beyond the action bounds, the follower losing its leader) it is skipped with a
one-line ``message``; nothing is raised.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import PSI_FIELDS, SectionTruth
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.idm_fit import IdmParams, calibrate_idm
from macromicro_sumo.evaluation.leader_follower import (
    FOLLOWER,
    LEADER,
    SCENARIOS,
    Follower,
    LeaderProfile,
    check_followers,
    idm_follower,
    leader_speeds,
    mean_idm_params,
    policy_follower,
    run_tests,
)
from macromicro_sumo.evaluation.micro_data import micro_pairs
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.physics import leader_length_m
from macromicro_sumo.road.section import Section

SKIPPED = "leader-follower tests skipped"
NO_LANE_CHANGE = 0  # SUMO lane-change mode: no lane change of any kind
END_MARGIN_M = 1.0  # the leader's front stays this far before an open section's end
MAX_SPACING_SCENES = 400  # scenes the ground truth's mean spacing is measured on


@dataclass(frozen=True)
class SectionLeaderFollower:
    """The tests on a section, or why they did not run.

    Attributes:
        traces: ``leader_follower.csv``'s rows (None: skipped).
        summary: ``leader_follower_summary.csv``'s rows (None: skipped).
        reference: what the ``IDM`` rows (the ground-truth follower) are.
        message: one line: what ran, or ``SKIPPED`` and why.
    """

    traces: pd.DataFrame | None
    summary: pd.DataFrame | None
    reference: str
    message: str

    @property
    def skipped(self) -> bool:
        return self.traces is None


# --------------------------------------------------------------------------- the road


def lane_path(section: Section) -> np.ndarray | None:
    """One lane index per edge (E,): a lane of the first edge from which a vehicle reaches
    the section's end (a loop: comes round) on every edge's lane that is on the path, by the
    network's connections alone; the rightmost such lane, then per edge the same index
    where it is on the path, else the rightmost one. None: no lane does."""
    n, m = len(section.edge_ids), section.max_lanes
    exists = np.arange(m)[None, :] < section.n_lanes[:, None]
    good = exists & ~section.lane_ends
    # Lanes that lead on to a good lane: from the open end backwards, round a loop until
    # nothing changes (a lane that feeds only dead ends is no path).
    for _ in range(n * m + 1 if section.closed else 1):
        before = good.copy()
        for e in reversed(range(n if section.closed else n - 1)):
            nxt = good[(e + 1) % n]
            good[e] &= (section.links[e] & nxt[None, :]).any(axis=1)
        if (good == before).all():
            break
    if not good[0].any():
        return None
    path = np.zeros(n, dtype=np.int64)
    path[0] = int(np.flatnonzero(good[0])[0])
    for e in range(n - 1):
        succ = np.flatnonzero(section.links[e, path[e]] & good[e + 1])
        path[e + 1] = path[e] if path[e] in succ else int(succ[0])
    return path


def path_limit(section: Section, path: np.ndarray) -> float:
    """The highest speed limit on the lane path [m/s]."""
    return float(np.nanmax(section.limits_mps[np.arange(len(path)), path]))


def _shift_onto_edge(section: Section, arc_m: float) -> float:
    """How far [m] ``arc_m`` must move downstream to lie on an edge 1 m clear of its ends
    (the core places vehicles on edges, not in junctions); 0 where it does already."""
    n = len(section.edge_ids)
    a = float(np.mod(arc_m, section.length_m)) if section.closed else float(arc_m)
    e = int(section.edge_index(np.array([a]))[0])
    rel = a - float(section.offsets_m[e])
    if rel < 1.0:
        return 1.0 - rel
    if rel <= float(section.lengths_m[e]) - 1.0:
        return 0.0
    if e + 1 < n:
        return float(section.offsets_m[e + 1]) + 1.0 - a
    return section.length_m + 1.0 - a if section.closed else np.inf


def start_arc(section: Section, spacing_m: float, vehicle_length_m: float) -> float | None:
    """The follower's start arc: 0 on a loop (the ring's; its edge starts at 0, so the
    vehicle's back hangs over the closing junction as on the ring), one vehicle length on
    an open section; moved downstream until neither vehicle starts in a junction. None:
    no such place."""
    s = 0.0 if section.closed else vehicle_length_m
    for _ in range(4 * len(section.edge_ids)):
        mine = 0.0 if section.closed and s == 0.0 else _shift_onto_edge(section, s)
        shift = max(mine, _shift_onto_edge(section, s + spacing_m))
        if shift == 0.0:
            return s
        if not np.isfinite(shift):
            return None
        s += shift
    return None


def section_bank(
    section: Section,
    path: np.ndarray,
    profile: LeaderProfile,
    start_m: float,
    vehicle_length_m: float,
    dt_s: float,
) -> SectionBank:
    """Two-vehicle episodes, one per scenario in ``SCENARIOS`` order: follower 0 at
    ``start_m``, leader 1 ``profile.spacing_m`` ahead on the lane path, both at the leader's
    start speed and both hidden (the leader is commanded its profile)."""
    lead = np.stack([leader_speeds(s, profile, dt_s) for s in SCENARIOS])  # (E, H + 1)
    e, h1 = lead.shape
    arc = section.wrap(np.array([start_m, start_m + profile.spacing_m]))
    lane = path[section.edge_index(arc)]
    nan = np.full((e, h1, 2), np.nan)
    none = np.zeros((e, h1, 0))
    # Psi only enters the macro reward, which these tests ignore; any valid one will do.
    psi = dict.fromkeys(PSI_FIELDS, 1.0) | {
        "mean_speed_mps": profile.low_speed_mps,
        "mean_spacing_m": profile.spacing_m,
        "speed_max_mps": profile.high_speed_mps,
        "spacing_min_m": vehicle_length_m,
    }
    return SectionBank(
        lane0=np.tile(lane, (e, 1)),
        arc0_m=np.tile(arc, (e, 1)),
        speed0_mps=np.repeat(lead[:, :1], 2, axis=1),
        length_m=np.full((e, 2), vehicle_length_m),
        valid=np.ones((e, 2), dtype=bool),
        hidden=np.ones((e, 2), dtype=bool),
        psi=np.tile([psi[f] for f in PSI_FIELDS], (e, 1)),
        replay_lane=nan,
        replay_arc_m=nan,
        replay_speed_mps=nan,
        gt_accel_mps2=nan[:, 1:],
        true_lane=none,
        true_arc_m=none,
        true_speed_mps=none,
        true_valid=none.astype(bool),
        true_length_m=np.zeros((e, 0)),
        run=np.zeros(e, dtype=np.int64),
        time_s=np.zeros(e),
    )


# --------------------------------------------------------------------------- the tests


def run_leader_follower_for(
    sc,
    section: Section,
    net_file: Path,
    followers: Mapping[str, Follower],
    idm_params: Mapping[str, float],
    mean_spacing_m: float,
    vehicle_length_m: float,
    n_trials: int,
    seed: int,
    profile: LeaderProfile | None = None,
    vclass: str = "passenger",
    reference: str = "IDM",
) -> SectionLeaderFollower:
    """Both scenarios on the section: ``run_tests`` with IDM of ``idm_params`` as reference.

    ``profile`` (default ``LeaderProfile()``) is stated for the paper's ring and runs as
    ``profile.moved(limit, mean_spacing_m)``, the uniform limit the fleet's upper one where
    the scenario has ``[speed_limits]``, else the highest on the lane path.
    ``reference`` names the ``IDM`` rows in the result. Skipped (a one-line message) where
    the section cannot hold the test.
    """
    check_followers(followers, n_trials)
    where = f"{getattr(sc, 'source', '') or 'scenario'}"

    def skip(why: str) -> SectionLeaderFollower:
        return SectionLeaderFollower(None, None, reference, f"{SKIPPED} ({where}): {why}")

    path = lane_path(section)
    if path is None:
        return skip("no lane of the first edge leads through the section without a lane change")
    limits = getattr(sc, "speed_limits", None)
    speed_limit_mps = limits.range_mps[1] if limits is not None else path_limit(section, path)
    moved = (profile or LeaderProfile()).moved(speed_limit_mps, mean_spacing_m)
    dt = sc.simulation.step_length_s
    a_min, a_max = sc.bounds.accel_mps2
    if moved.ramp_mps2 > min(a_max, -a_min):
        return skip(
            f"the leader's ramp {moved.ramp_mps2:.3g} m/s^2 lies outside the action bounds "
            f"bounds.accel_mps2 = [{a_min:g}, {a_max:g}]"
        )
    lead = np.stack([leader_speeds(s, moved, dt) for s in SCENARIOS])
    start = start_arc(section, moved.spacing_m, vehicle_length_m)
    length = section.length_m
    if section.closed:
        if not vehicle_length_m < moved.spacing_m < length - vehicle_length_m or start is None:
            return skip(
                f"a start spacing of {moved.spacing_m:.1f} m does not fit two "
                f"{vehicle_length_m:g} m vehicles on the {length:.1f} m loop"
            )
    else:
        travel = float(lead[:, 1:].sum(axis=1).max() * dt)
        need = vehicle_length_m + moved.spacing_m + travel + END_MARGIN_M
        if start is None or need > length:
            return skip(
                f"the section is {length:.0f} m long; the test needs {need:.0f} m "
                f"(the leader starts {moved.spacing_m:.0f} m ahead and drives {travel:.0f} m "
                f"in evaluation.lf_duration_s = {moved.duration_s:g} s at "
                f"{moved.low_speed_mps:.1f}-{moved.high_speed_mps:.1f} m/s)"
            )
    uniform = replace(
        section,
        limits_mps=np.where(np.isnan(section.limits_mps), np.nan, float(speed_limit_mps)),
    )
    bank = section_bank(uniform, path, moved, start, vehicle_length_m, dt)
    # What a model subtracts from the observation's leader column (a gap layout: nothing).
    lead_m = leader_length_m(sc.policy.observation, vehicle_length_m)
    idm = idm_follower(idm_params, lead_m)
    core = SectionCore(sc, uniform, bank, net_file, seed=seed, vclass=vclass, safety="none")
    core.rewarded = False  # the traces are speeds and gaps: r_macro would go unread
    lanes = list(section.lanes)
    # SUMO's lane limits as the observation's: the insertion speed is capped at them.
    core.sim.set_lane_speed_limits(lanes, [float(speed_limit_mps)] * len(lanes))

    def keep_lanes(c: SectionCore) -> None:
        c.sim.set_lane_change_mode([c.ids[FOLLOWER], c.ids[LEADER]], NO_LANE_CHANGE)

    try:
        traces, summary = run_tests(core, followers, idm, n_trials, seed, lead_m, lead, keep_lanes)
    except UserError as exc:  # the section could not hold a trial: say so, go on
        return skip(str(exc).removeprefix("leader-follower test: "))
    finally:
        core.close()
    return SectionLeaderFollower(
        traces,
        summary,
        reference,
        f"leader-follower tests ({where}): lanes {path.tolist()}, limit "
        f"{speed_limit_mps:.2f} m/s, leader {moved.low_speed_mps:.2f} <-> "
        f"{moved.high_speed_mps:.2f} m/s, start spacing {moved.spacing_m:.1f} m; reference: "
        f"{reference}",
    )


# --------------------------------------------------------------------------- the stage


def truth_mean_spacing(sc, truth: SectionTruth) -> float:
    """The ground truth's mean front-to-front spacing per lane [m] (vehicles with a leader
    on the section): L / N for a fleet on its loop (exact, the ring's); the recorded
    trajectories otherwise (on up to ``MAX_SPACING_SCENES`` scenes evenly through them);
    field data holds only the observed vehicles: their measured leaders where recorded,
    else the stations' 1 / density."""
    if getattr(sc, "fleet", None) is not None:
        return truth.section.length_m / sc.fleet.n_vehicles
    traj = truth.trajectories
    if sc.data.source == "files":
        if "leader_spacing_m" in traj and traj["leader_spacing_m"].notna().any():
            return float(traj["leader_spacing_m"].mean())
        return float(truth.macro["mean_spacing_m"].mean())
    scenes = traj.groupby(["run", "time_s"], sort=True).indices
    keys = list(scenes)
    pick = np.unique(np.linspace(0, len(keys) - 1, MAX_SPACING_SCENES).astype(np.int64))
    lane = traj["lane_index"].to_numpy(dtype=np.int64)
    arc = traj["arc_m"].to_numpy(dtype=float)
    spacings = []
    for i in pick:
        rows = scenes[keys[i]]
        lead, gap = section_leaders(truth.section, lane[rows], arc[rows])
        spacings.append(gap[lead >= 0])
    got = np.concatenate(spacings) if spacings else np.array([])
    if not got.size:
        raise UserError(f"{truth.folder}: no vehicle has a leader on the section")
    return float(got.mean())


def reference_idm(sc, truth: SectionTruth, vehicle_length_m: float) -> tuple[dict, str]:
    """The ground-truth follower's IDM parameters and what they are: the fleet's (the
    middle of its ranges, as the ring) or IDM fitted to every recorded vehicle."""
    if getattr(sc, "fleet", None) is not None:
        return mean_idm_params(sc), "the fleet's IDM, the middle of its [fleet] ranges"
    everyone = replace(truth, trajectories=truth.trajectories.assign(observed=True))
    obs, acc = micro_pairs(sc, everyone, truth.runs)
    params, rmse = calibrate_idm(obs, acc, leader_length_m(sc.policy.observation, vehicle_length_m))
    what = "the recorded vehicles" if sc.data.source == "files" else "every recorded vehicle"
    return _idm_dict(params), (
        f"IDM fitted to {what} of the ground truth ({len(acc)} pairs, fit RMSE "
        f"{rmse:.3f} m/s^2; no [fleet] of known IDM parameters)"
    )


def _idm_dict(p: IdmParams) -> dict[str, float]:
    return {k: float(v) for k, v in p.as_dict().items()}


def section_leader_follower_tests(
    sc,
    truth: SectionTruth,
    net_file: Path,
    agents: Mapping[str, object],
    idm_calibrated: IdmParams,
    vehicle_length_m: float,
    vclass: str = "passenger",
) -> SectionLeaderFollower:
    """The section evaluation's tests: every learned method (stochastic) and the calibrated
    IDM against the ground-truth follower, ``evaluation.lf_trials`` trials each."""
    followers: dict[str, Follower] = {n: policy_follower(a) for n, a in agents.items()}
    lead_m = leader_length_m(sc.policy.observation, vehicle_length_m)
    followers["idm_calibrated"] = idm_follower(_idm_dict(idm_calibrated), lead_m)
    params, what = reference_idm(sc, truth, vehicle_length_m)
    duration = sc.evaluation.lf_duration_s
    return run_leader_follower_for(
        sc,
        truth.section,
        net_file,
        followers,
        params,
        truth_mean_spacing(sc, truth),
        vehicle_length_m,
        sc.evaluation.lf_trials,
        sc.seed,
        LeaderProfile(duration_s=duration, hold_s=min(20.0, duration / 3)),
        vclass=vclass,
        reference=what,
    )

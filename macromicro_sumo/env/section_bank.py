"""The episodes of Stage II on a section of the user's network.

``SectionBank``: completed start scenes (observed vehicles + generated hidden vehicles),
the observed vehicles' recorded futures and every true vehicle over the horizon, built
from the ground truth's snapshots (``build_section_bank``); ``section_target`` and
``section_macro_reward``: what a scene's reward compares with, and the reward. What a
vehicle observes: ``env.section_observations``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from macromicro_sumo.data.objective import MacroTarget, macro_reward, macro_terms
from macromicro_sumo.data.section import (
    PSI_FIELDS,
    SectionSnapshots,
    SectionTruth,
    hidden_per_snapshot,
    run_limits_mps,
    signal_settings,
)
from macromicro_sumo.data.vtypes import typical
from macromicro_sumo.env.vtype_draw import generated_vtypes
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.leaders import STANDING_MIN_GAP_M, STOPLINE_GAP_M
from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.section import load_section


@dataclass(frozen=True)
class SectionBank:
    """Start scenes and recorded futures of many episodes; arrays over episodes (E, ...)."""

    lane0: np.ndarray  # (E, N) int lane index, completed scene (observed first, then generated)
    arc0_m: np.ndarray  # (E, N)
    speed0_mps: np.ndarray  # (E, N)
    length_m: np.ndarray  # (E, N) vehicle lengths
    valid: np.ndarray  # (E, N) bool: a vehicle in this slot
    hidden: np.ndarray  # (E, N) bool: generated (driven by the policy)
    psi: np.ndarray  # (E, len(PSI_FIELDS))
    # Recorded futures of the observed vehicles (NaN: off the section at that step).
    replay_lane: np.ndarray  # (E, H + 1, N) float lane index
    replay_arc_m: np.ndarray  # (E, H + 1, N)
    replay_speed_mps: np.ndarray  # (E, H + 1, N)
    gt_accel_mps2: np.ndarray  # (E, H, N) recorded actions (NaN: unknown)
    # Every true vehicle on the section over the horizon (the ground-truth method, evaluation).
    true_lane: np.ndarray  # (E, H + 1, M) float lane index
    true_arc_m: np.ndarray  # (E, H + 1, M)
    true_speed_mps: np.ndarray  # (E, H + 1, M)
    true_valid: np.ndarray  # (E, H + 1, M) bool
    true_length_m: np.ndarray  # (E, M)
    run: np.ndarray  # (E,)
    time_s: np.ndarray  # (E,)
    # (E, edges, max lanes) the episode's run's speed limits [m/s] (``run_limits_mps``: drawn
    # per run where the truth has speed_limits.csv); None: the section's own.
    limits_mps: np.ndarray | None = None
    # (E, N) each slot's desired-speed factor on the limits it observes (``policy.
    # driver_speed``, ``env.driver_speed``); None: 1 for every driver.
    driver_factor: np.ndarray | None = None
    # (E, N) each slot's Krauss tau [s] (``policy.driver_follow``, ``env.driver_tau``): the
    # policy's rollouts append it to the observations (``policy.rollout.own_taus``); None:
    # the prior's one tau.
    driver_tau: np.ndarray | None = None
    # (E, N) each slot's vType's maxSpeed [m/s] (``speed_caps``; inf: none): a hidden
    # vehicle's speed commands are held to it, its physics (as a deployment's); None: no cap.
    vmax_mps: np.ndarray | None = None
    # (E, N) each slot's vType's accel [m/s^2] (``vtype_caps``; inf: none): a hidden
    # vehicle accelerates at most at it, its physics (as a deployment's); None: no cap.
    accel_mps2: np.ndarray | None = None
    # (E,) object: the section's signals at the episode's start as the truth recorded them
    # (``data.section.signal_settings``), set at reset; None: no signal recorded.
    signals: np.ndarray | None = None
    # (E, N) each slot's vType's minGap and jmStoplineGap [m] (``standing_gaps``): where its
    # driver stands before a standing leader (``road.leaders.standing_spacing_m``); None:
    # SUMO's defaults (2.5 and 1 m) for every slot.
    min_gap_m: np.ndarray | None = None
    stopline_gap_m: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.run)

    @property
    def horizon(self) -> int:
        return self.replay_speed_mps.shape[1] - 1

    @property
    def observed(self) -> np.ndarray:
        return self.valid & ~self.hidden

    def take(self, idx: np.ndarray) -> SectionBank:
        """The episodes ``idx`` only."""
        return SectionBank(
            **{
                f: None if getattr(self, f) is None else getattr(self, f)[idx]
                for f in self.__dataclass_fields__
            }
        )

    def gaps_of(self, episode: int) -> dict[str, np.ndarray | None]:
        """Episode ``episode``'s minGap and jmStoplineGap per slot, as ``section_observations``
        takes them (None: SUMO's defaults)."""
        return {
            k: None if getattr(self, k) is None else getattr(self, k)[episode]
            for k in ("min_gap_m", "stopline_gap_m")
        }

    def factor_of(self, episode: int) -> np.ndarray | None:
        """Episode ``episode``'s desired-speed factors per slot (None: all 1)."""
        return None if self.driver_factor is None else self.driver_factor[episode]

    def section_of(self, section: Section, episode: int) -> Section:
        """``section`` with episode ``episode``'s speed limits (itself where they agree)."""
        lim = None if self.limits_mps is None else self.limits_mps[episode]
        if lim is None or np.array_equal(lim, section.limits_mps, equal_nan=True):
            return section
        return dataclasses.replace(section, limits_mps=lim)


Completion = Callable[
    [SectionSnapshots], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
]


def build_section_bank(
    sc,
    truth: SectionTruth,
    snaps: SectionSnapshots,
    completion: Completion,
    horizon: int | None = None,
    seed: int = 0,
) -> SectionBank:
    """Episodes from ``snaps``: completed start scenes plus the recorded futures;
    ``completion(snaps) -> (lane, arc, speed, valid, generated)``, each (S, N'), observed
    vehicles first then the generated ones (the generator's ``SectionCompletion``, or the
    true hidden vehicles for tests). Observed vehicles are found in the trajectories by (run,
    time, lane, arc); snapshots with fewer than ``horizon`` recorded steps after them are
    dropped. ``seed``: the generated vehicles' vTypes where drawn (``generated_vtypes``)."""
    h = horizon or sc.policy.horizon
    dt = sc.simulation.step_length_s
    traj = truth.trajectories
    length_of = dict(zip(truth.vtypes["vtype"], truth.vtypes["length_m"], strict=True))
    caps, accels = vtype_caps(sc, truth)
    gaps = standing_gaps(sc, truth)  # per vType: minGap, jmStoplineGap (none: the defaults)
    runs: dict[int, dict[str, np.ndarray]] = {}
    for r, g in traj.groupby("run", sort=True):
        g = g.sort_values("time_s", kind="stable")
        runs[int(r)] = {
            "time": g["time_s"].to_numpy(dtype=float),
            "vid": g["vehicle_id"].to_numpy(dtype=object),
            "lane": g["lane_index"].to_numpy(dtype=float),
            "arc": g["arc_m"].to_numpy(dtype=float),
            "speed": g["speed_mps"].to_numpy(dtype=float),
            "observed": recordable(sc, g),
            "length": g["vtype"].map(length_of).to_numpy(dtype=float),
            "vmax": g["vtype"].map(caps).fillna(np.inf).to_numpy(dtype=float),
            "accel": g["vtype"].map(accels).fillna(np.inf).to_numpy(dtype=float),
            **{
                k: g["vtype"].map(of).fillna(default).to_numpy(dtype=float)
                for k, (of, default) in gaps.items()
            },
        }
    keep = with_future(truth, snaps, h, dt)
    if not keep.size:
        raise UserError(f"{truth.folder}: no snapshot leaves {h} steps of recorded future")
    snaps = snaps.take(keep)
    lane, arc, speed, valid, generated = (np.asarray(x) for x in completion(snaps))
    valid = valid.astype(bool)
    hidden = valid & generated.astype(bool)
    e_n, n = arc.shape
    replay = np.full((3, e_n, h + 1, n), np.nan)
    length = np.zeros((e_n, n))
    vmax, accel = np.full((e_n, n), np.inf), np.full((e_n, n), np.inf)
    gap = {k: np.full((e_n, n), default) for k, (_, default) in gaps.items()}
    windows = []
    for i, (r, t0) in enumerate(zip(snaps.run, snaps.time_s, strict=True)):
        d = runs[int(r)]
        lo, hi = np.searchsorted(d["time"], [t0 - 1e-6, t0 + h * dt + 1e-6])
        w = {k: v[lo:hi] for k, v in d.items()}
        w["step"] = np.rint((w["time"] - t0) / dt).astype(np.int64)
        windows.append(w)
        at0 = np.flatnonzero(w["step"] == 0)
        slot_of = {}
        for j in np.flatnonzero(valid[i] & ~hidden[i]):
            cand = at0[(w["lane"][at0] == lane[i, j]) & w["observed"][at0]]
            if cand.size == 0:
                raise UserError(
                    f"run {r}, t = {t0:g} s: observed vehicle at lane {lane[i, j]}, "
                    f"{arc[i, j]:.2f} m is not in the trajectories"
                )
            k = cand[np.argmin(np.abs(w["arc"][cand] - arc[i, j]))]
            if abs(w["arc"][k] - arc[i, j]) > 1e-3:
                raise UserError(
                    f"run {r}, t = {t0:g} s: no recorded observed vehicle at lane "
                    f"{lane[i, j]}, {arc[i, j]:.2f} m"
                )
            slot_of[w["vid"][k]] = j
            length[i, j], vmax[i, j], accel[i, j] = w["length"][k], w["vmax"][k], w["accel"][k]
            for name, per in gap.items():
                per[i, j] = w[name][k]
        for k in range(len(w["time"])):
            j = slot_of.get(w["vid"][k])
            if j is not None:
                s = w["step"][k]
                replay[:, i, s, j] = w["lane"][k], w["arc"][k], w["speed"][k]
    # A generated vehicle is the typical vType (or one drawn: ``generated_vtypes``), its
    # length, maxSpeed and accel.
    gen = generated_vtypes(sc, truth.vtypes, typical_vtype(truth), int(hidden.sum()), seed)
    length[hidden] = [length_of[v] for v in gen]
    vmax[hidden] = [caps.get(v, np.inf) for v in gen]
    accel[hidden] = [accels.get(v, np.inf) for v in gen]
    for name, (of, default) in gaps.items():
        gap[name][hidden] = [of.get(v, default) for v in gen]
    # ... and starts at most at it: above it SUMO would slow it down in the first step, a
    # deceleration that no driver chose (its commands are held to it from then on).
    speed = np.where(hidden & valid, np.minimum(speed, vmax), speed)
    spd = replay[2]
    with np.errstate(invalid="ignore"):
        gt_accel = np.diff(spd, axis=1) / dt  # NaN where either end is off the section
    true = _true_scenes(windows, h)
    return SectionBank(
        lane0=lane.astype(np.int64),
        arc0_m=arc.astype(float),
        speed0_mps=speed.astype(float),
        length_m=length,
        valid=valid,
        hidden=hidden,
        psi=snaps.psi,
        replay_lane=replay[0],
        replay_arc_m=replay[1],
        replay_speed_mps=replay[2],
        gt_accel_mps2=gt_accel,
        true_lane=true[0],
        true_arc_m=true[1],
        true_speed_mps=true[2],
        true_valid=np.isfinite(true[2]),
        true_length_m=true[3][:, 0, :],
        run=snaps.run,
        time_s=snaps.time_s,
        limits_mps=run_limits_mps(truth, snaps.run),
        vmax_mps=vmax if np.isfinite(vmax).any() else None,  # None: nothing to cap
        accel_mps2=accel if np.isfinite(accel).any() else None,
        signals=signal_settings(truth.signals, snaps.run, snaps.time_s),
        **{k: v if gaps[k][0] else None for k, v in gap.items()},  # None: the defaults
    )


def set_sumo_limits(sim, section: Section, now_mps: np.ndarray) -> np.ndarray:
    """Give the lanes of the section's edges in ``sim`` (a ``Simulation``) the limits of
    ``section`` (a run's, as the truth set them: SUMO's drivers and its departure check read
    them) where they differ from ``now_mps``, what SUMO has; returns what it has then."""
    if np.array_equal(section.limits_mps, now_mps, equal_nan=True):
        return now_mps
    pairs = [
        (lane, float(section.limits_mps[e, i]))
        for e, lanes in enumerate(section.edge_lane_ids)
        for i, lane in enumerate(lanes)
    ]
    sim.set_lane_speed_limits([a for a, _ in pairs], [b for _, b in pairs])
    return section.limits_mps


def with_future(
    truth: SectionTruth, snaps: SectionSnapshots, horizon: int, dt: float
) -> np.ndarray:
    """Indices of the snapshots with ``horizon`` recorded steps after them: the episodes
    ``build_section_bank`` keeps, in order."""
    last = truth.trajectories.groupby("run")["time_s"].max()
    ends = last.reindex(snaps.run.astype(np.int64)).to_numpy(dtype=float)
    with np.errstate(invalid="ignore"):  # a run with no record: NaN, dropped
        return np.flatnonzero(snaps.time_s + horizon * dt <= ends + 1e-6)


def recordable(sc, traj) -> np.ndarray:
    """Which rows of ``traj`` a snapshot's observed vehicles can be: the instrumented ones,
    or every recorded vehicle with ``instrumented.hidden = "snapshot"`` (its hidden sets
    are drawn per snapshot: ``data.section.hide_random``)."""
    if hidden_per_snapshot(sc):
        return np.ones(len(traj), dtype=bool)
    return traj["observed"].to_numpy(dtype=bool)


def _typical(truth: SectionTruth, column: str) -> object:
    """``column`` of the vType with the most vehicles on the section (generated vehicles')."""
    return typical(truth.vtypes, column)


def typical_vclass(truth: SectionTruth) -> str:
    """SUMO vehicle class for our vehicles: that of the vType with the most vehicles (lanes
    may admit only some classes, e.g. a race track only ``vip``)."""
    return str(_typical(truth, "vclass")) if "vclass" in truth.vtypes else "passenger"


def typical_vtype(truth: SectionTruth) -> str:
    """The vType of generated vehicles: the one with the most vehicles on the section."""
    return str(_typical(truth, "vtype"))


def typical_length(truth: SectionTruth) -> float:
    """Length of generated vehicles: the vType with the most vehicles on the section."""
    return float(_typical(truth, "length_m"))


def speed_caps(sc, truth: SectionTruth) -> dict[str, float]:
    """Per vType of the demand its vehicles' maxSpeed [m/s] where the vType sets one (the
    vehicle's cap: SUMO never drives it faster, whatever its driver wants); none for field
    data (``data.source = "files"``), which has no vTypes."""
    return vtype_caps(sc, truth)[0]


def vtype_caps(sc, truth: SectionTruth) -> tuple[dict[str, float], dict[str, float]]:
    """Per vType of the demand, where the vType sets them, its maxSpeed [m/s]
    (``speed_caps``) and its accel [m/s^2] (SUMO's Krauss and IDM never accelerate harder;
    the deployment holds every command to it, ``road.vtype``). Where a vType sets none
    has its vClass's defaults, not known without SUMO: no cap (a passenger car's accel,
    2.6 m/s^2, is at least every shipped scenario's bound; a truck's, 1.3, is not). None
    for field data (``data.source = "files"``), which has no vTypes."""
    if sc.data.source == "files" or truth.vtypes.empty:
        return {}, {}
    _, _, vtypes = load_section(sc)
    speed, accel = (
        {k: float(t.params[name]) for k, t in vtypes.items() if name in t.params}
        for name in ("maxSpeed", "accel")
    )
    return speed, accel


def standing_gaps(sc, truth: SectionTruth) -> dict[str, tuple[dict[str, float], float]]:
    """Per vType of the demand, as ``vtypes.csv`` records them, its minGap and jmStoplineGap
    [m] (``min_gap_m``, ``stopline_gap_m``), each with SUMO's default for the vTypes it
    does not know: where its driver stands before a standing leader. None known (no such
    column, a vType without a value): the defaults; field data (``data.source =
    "files"``), whose vtypes.csv minGap is the scenario's, keeps them."""
    vt = truth.vtypes
    out = {}
    for col, default in (("min_gap_m", STANDING_MIN_GAP_M), ("stopline_gap_m", STOPLINE_GAP_M)):
        known = {}
        if col in vt and sc.data.source != "files":
            rows = vt[["vtype", col]].dropna()
            known = dict(zip(rows["vtype"], rows[col].astype(float), strict=True))
        out[col] = (known, default)
    return out


def recorded_min_gap(truth: SectionTruth) -> float | None:
    """The smallest minGap of the recorded vehicles' vTypes [m] (None: not recorded)."""
    vt = truth.vtypes
    if "min_gap_m" not in vt or not len(vt):
        return None
    return float(vt["min_gap_m"].min())


def _true_scenes(windows: list[dict[str, np.ndarray]], h: int) -> np.ndarray:
    """(lane, arc, speed, length) of every true vehicle per episode step: (4, E, H + 1, M);
    slots in order of first appearance (the start scene first)."""
    slots = []
    for w in windows:
        _, first = np.unique(w["vid"], return_index=True)
        order = np.sort(first)
        slots.append({w["vid"][k]: j for j, k in enumerate(order)})
    m = max(1, max(len(s) for s in slots))
    out = np.full((4, len(windows), h + 1, m), np.nan)
    for i, (w, s) in enumerate(zip(windows, slots, strict=True)):
        j = np.array([s[v] for v in w["vid"]], dtype=np.int64)
        out[:, i, w["step"], j] = w["lane"], w["arc"], w["speed"], w["length"]
    # A vehicle's length holds at every step: fill it along the horizon for step 0's use.
    longest = np.where(np.isnan(out[3]), -np.inf, out[3]).max(axis=1, keepdims=True)
    out[3] = np.where(np.isfinite(longest), longest, np.nan)
    return out


_PSI = {f: i for i, f in enumerate(PSI_FIELDS)}


def section_target(psi: np.ndarray) -> MacroTarget:
    """What a section scene's reward compares with: psi's fields (no upper spacing bound:
    L_max is 0; L_var is the measured dispersion where the detectors measured a spacing
    std, else the paper's). Built once per episode."""
    return MacroTarget(
        psi[_PSI["mean_speed_mps"]],
        psi[_PSI["mean_spacing_m"]],
        psi[_PSI["spacing_min_m"]],
        np.float64(np.inf),
        spacing_std_m=psi[_PSI["std_spacing_m"]],
    )


def section_macro_reward(
    speed_mps: np.ndarray,
    spacing_m: np.ndarray,
    leader: np.ndarray,
    hidden: np.ndarray,
    active: np.ndarray,
    target: MacroTarget,
    lambda_v: float,
    lambda_d: float,
    speed_scale_mps: float = 0.0,
) -> tuple[float, dict[str, float]]:
    """r_macro of the active vehicles against ``target`` (``data.objective``, as on the ring).

    L_speed on the mean speed of all active vehicles; A holds the per-lane spacings that
    touch a hidden vehicle (it, or its leader), vehicles without a leader excluded.
    """
    if not active.any():
        return 0.0, {}
    in_a = active & (leader >= 0) & (hidden | hidden[np.maximum(leader, 0)])
    # Already selected, as on the ring: no masks to multiply on this hot path.
    terms = macro_terms(speed_mps[active], None, spacing_m[in_a], None, target, speed_scale_mps)
    terms = {k: float(v) for k, v in terms.items()}
    return float(macro_reward(terms, lambda_v, lambda_d)), terms

"""``idm_true`` on a section: each hidden vehicle driven by its own ground-truth IDM
parameters, an oracle bound (what no calibration of one shared model can beat by knowing
more about the drivers).

It needs a truth that knows every vehicle's parameters: a ``[fleet]`` demand, whose draws
``vehicles.csv`` records per run and vehicle (``truth.fleet``; every vehicle IDM). Route
files do not: their vTypes may have other models, and SUMO draws each vehicle's speed
factor from the vType's distribution without recording it, so there ``true_idm_table``
says why the method is left out instead.

The generated vehicles of a scene are not the hidden ones, so each takes the parameters of
the true hidden vehicle it is matched to: one to one by least arc distance (around the
loop on a closed section), as the ring matches them; where the generator placed more
vehicles than were hidden (an estimated hidden count above the true one) each extra one
takes its nearest true hidden vehicle's, and in a scene with none hidden its nearest
recorded vehicle's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from macromicro_sumo.data.section import SectionSnapshots, SectionTruth
from macromicro_sumo.env.rollout import ActionFn
from macromicro_sumo.env.section_bank import SectionBank
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.idm_fit import IdmParams, idm_policy_accel
from macromicro_sumo.files import read_checked_csv, read_manifest

VEHICLES = "vehicles.csv"
PARAMS = ("speed_factor", "tau_s", "accel_mps2", "decel_mps2", "min_gap_m", "delta")
# A true vehicle is the snapshot's slot when its recorded arc is this close [m].
ARC_MATCH_M = 1e-3


def true_idm_table(truth: SectionTruth) -> tuple[pd.DataFrame | None, str]:
    """(each vehicle's IDM parameters indexed by (run, vehicle_id), one line for the log)
    where the truth records them (a fleet's ``vehicles.csv``); (None, why not) elsewhere."""
    if not (truth.folder / VEHICLES).is_file():
        vt = truth.vtypes
        models = sorted(set(vt["car_follow_model"].astype(str))) if "car_follow_model" in vt else []
        which = f" (car-following models {', '.join(models)})" if models else ""
        return None, (
            f"idm_true (oracle) left out: the ground truth {truth.folder} records no "
            f"per-vehicle IDM parameters ({VEHICLES}, written for a [fleet] demand); its "
            f"demand is route files{which}"
        )
    manifest = read_manifest(truth.folder / "manifest.json")
    table = read_checked_csv(
        truth.folder,
        VEHICLES,
        manifest,
        ("run", "vehicle_id", *PARAMS),
        PARAMS,
        dtype={"vehicle_id": str},
    )
    table = table.set_index(["run", "vehicle_id"])
    return table, f"idm_true: each hidden vehicle's own IDM parameters ({truth.folder / VEHICLES})"


def _arc_distance(a: np.ndarray, b: np.ndarray, loop_m: float | None) -> np.ndarray:
    """|a_i - b_j| [m] for every pair, around the loop where ``loop_m`` is its length."""
    d = a[:, None] - b[None, :]
    if loop_m is not None:
        d = np.mod(d + loop_m / 2, loop_m) - loop_m / 2
    return np.abs(d)


def _scene_ids(truth: SectionTruth, snaps: SectionSnapshots) -> list[np.ndarray]:
    """Per snapshot, the recorded vehicle of each slot (None in padding): found in the
    trajectories by (run, time, lane, arc), as ``build_section_bank`` finds observed ones."""
    traj = truth.trajectories
    traj = traj[traj["run"].isin(np.unique(snaps.run))]
    by_scene = {(int(r), round(float(t), 6)): g for (r, t), g in traj.groupby(["run", "time_s"])}
    out = []
    for i, (run, t) in enumerate(zip(snaps.run, snaps.time_s, strict=True)):
        g = by_scene.get((int(run), round(float(t), 6)))
        ids = np.full(snaps.valid.shape[1], None, dtype=object)
        for j in np.flatnonzero(snaps.valid[i]):
            if g is None:
                raise UserError(
                    f"{truth.folder}: run {run}, t = {t:g} s is not in the trajectories"
                )
            on_lane = g[g["lane_index"].to_numpy() == snaps.lane[i, j]]
            err = np.abs(on_lane["arc_m"].to_numpy() - snaps.arc_m[i, j])
            if not err.size or err.min() > ARC_MATCH_M:
                raise UserError(
                    f"{truth.folder}: run {run}, t = {t:g} s: no recorded vehicle at lane "
                    f"{snaps.lane[i, j]}, {snaps.arc_m[i, j]:.2f} m"
                )
            ids[j] = on_lane["vehicle_id"].iloc[int(np.argmin(err))]
        out.append(ids)
    return out


def true_idm_by_episode(
    truth: SectionTruth, table: pd.DataFrame, snaps: SectionSnapshots, bank: SectionBank
) -> list[IdmParams]:
    """Per episode of ``bank`` (built from ``snaps``, one episode per snapshot in order),
    the true IDM parameters of its generated vehicles, in their slot order (the order an
    action function returns accelerations in)."""
    if len(snaps) != len(bank):
        raise ValueError(f"{len(snaps)} snapshots for {len(bank)} episodes")
    loop = truth.section.length_m if truth.section.closed else None
    ids = _scene_ids(truth, snaps)
    out = []
    for e in range(len(bank)):
        gen = np.flatnonzero(bank.hidden[e])
        pool = np.flatnonzero(snaps.hidden[e])
        if not pool.size:  # nothing hidden here: the nearest recorded vehicle's
            pool = np.flatnonzero(snaps.valid[e])
        cost = _arc_distance(bank.arc0_m[e, gen], snaps.arc_m[e, pool], loop)
        match = cost.argmin(axis=1) if gen.size else np.zeros(0, dtype=np.int64)
        rows, cols = linear_sum_assignment(cost) if gen.size else ((), ())
        match[np.asarray(rows, dtype=np.int64)] = cols  # one to one where counts allow
        keys = [(int(bank.run[e]), ids[e][pool[m]]) for m in match]
        p = table.loc[keys, list(PARAMS)] if keys else table.iloc[:0][list(PARAMS)]
        delta = float(p["delta"].iloc[0]) if len(p) else 4.0
        out.append(IdmParams(*(p[c].to_numpy(dtype=float) for c in PARAMS[:-1]), delta))
    return out


def true_idm_action(params: list[IdmParams], veh_length_m: float) -> ActionFn:
    """The action function of ``idm_true``: each generated vehicle by its matched true
    vehicle's IDM (``true_idm_by_episode``)."""

    def act(core: Any, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return idm_policy_accel(obs[core.hidden], params[core.episode], veh_length_m)

    return act

"""Micro data of a section: the observed vehicles' (observation, action) pairs.

One definition for every stage that fits or judges a driver on them: the evaluation's
``idm_calibrated`` and micro consistency, the policy's prior, the leader-follower tests'
reference IDM and the deployment's calibrated IDM; and the IDM as a method on them.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.data.section import SectionTruth, recorded_steps, run_section, stop_lines_at
from macromicro_sumo.env.driver_tau import with_tau
from macromicro_sumo.env.rollout import ActionFn
from macromicro_sumo.env.section_bank import recordable, standing_gaps
from macromicro_sumo.env.section_observations import section_observations
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.idm_fit import IdmParams, idm_policy_accel
from macromicro_sumo.fielddata.leaders import has_measured_leaders, with_measured_leaders
from macromicro_sumo.road.physics import observes_gap, observes_length


def micro_pairs(
    sc, truth: SectionTruth, runs: np.ndarray, max_pairs: int = 20_000
) -> tuple[np.ndarray, np.ndarray]:
    """Observed vehicles' (observation, action) pairs: what their own sensors saw (the true
    scene around them) and the acceleration they applied over the next step. With
    ``instrumented.hidden = "snapshot"`` every recorded vehicle's (the ring's micro data)."""
    return keyed_micro_pairs(sc, truth, runs, max_pairs)[:2]


def keyed_micro_pairs(
    sc, truth: SectionTruth, runs: np.ndarray, max_pairs: int = 20_000
) -> tuple[np.ndarray, np.ndarray, list[tuple[int, str]]]:
    """``micro_pairs`` with each pair's driver, (run, vehicle ID) as
    ``env.observed_drivers.observed_drivers`` keys it: the key a driver's own fitted tau is
    found by (``evaluation.driver_follow.pair_taus``)."""
    dt = sc.simulation.step_length_s
    traj = truth.trajectories[truth.trajectories["run"].isin(runs)]
    measured = has_measured_leaders(traj)
    # Lengths: an own feature, and a standing leader's spacing (road.leaders.standing_spacing_m).
    # A gap layout needs the leaders' lengths too.
    need = observes_length(sc.policy.observation) or observes_gap(sc.policy.observation)
    lengths = _lengths(truth, traj, required=need)
    # Each recorded vehicle's length by id: a measured leader's (fielddata.leaders).
    by_id = None if lengths is None else pd.Series(lengths.to_numpy(), traj["vehicle_id"])
    # Each vType's minGap and jmStoplineGap: where its driver stands before a standing leader.
    types = traj["vtype"] if "vtype" in traj else pd.Series("", index=traj.index)
    gaps = {k: types.map(of).fillna(d) for k, (of, d) in standing_gaps(sc, truth).items()}
    obs_rows, acc_rows, keys = [], [], []
    for run, g in traj.groupby("run", sort=True):
        # The run's own speed limits (a fleet draws them per run), as the env observes them.
        section = run_section(truth, int(run))
        # A red or yellow stop line is a standing leader, as in the envs (data.section).
        stops = stop_lines_at(truth, int(run), np.unique(g["time_s"].to_numpy()))
        for s, speed_next in recorded_steps(g, dt):
            o = recordable(sc, s)
            if not o.any():
                continue
            obs, leader, _ = section_observations(
                section,
                s["lane_index"].to_numpy(),
                s["arc_m"].to_numpy(),
                s["speed_mps"].to_numpy(),
                np.ones(len(s), dtype=bool),
                sc.policy.observation,
                *stops.get(round(float(s["time_s"].iloc[0]), 6), (None, None)),
                length_m=None if lengths is None else lengths.loc[s.index].to_numpy(dtype=float),
                **{k: v.loc[s.index].to_numpy(dtype=float) for k, v in gaps.items()},
            )
            if measured:  # field data: the leader each vehicle measured (fielddata.leaders)
                obs, _ = with_measured_leaders(obs, leader, s, sc.policy.observation, by_id)
            ids = s["vehicle_id"].to_numpy()[o]
            v1 = np.array([speed_next.get(v, np.nan) for v in ids])
            a = (v1 - s["speed_mps"].to_numpy()[o]) / dt
            keep = np.isfinite(a)
            obs_rows.append(obs[o][keep])
            acc_rows.append(a[keep])
            keys += [(int(run), str(v)) for v in ids[keep]]
    if not obs_rows:
        raise UserError(f"{truth.folder}: no observed vehicle pair in runs {list(runs)}")
    obs, acc = np.concatenate(obs_rows), np.concatenate(acc_rows)
    if len(acc) > max_pairs:  # evenly thinned: neighbouring steps say nearly the same
        idx = np.linspace(0, len(acc) - 1, max_pairs).astype(np.int64)
        obs, acc, keys = obs[idx], acc[idx], [keys[i] for i in idx]
    return obs, acc, keys


def _lengths(truth: SectionTruth, traj: pd.DataFrame, required: bool) -> pd.Series | None:
    """Each trajectory row's vehicle length [m], its vType's (``vtypes.csv``); where one is
    unknown an error if ``required``, else None."""
    vt = truth.vtypes
    length_of = dict(zip(vt["vtype"], vt["length_m"], strict=True)) if "length_m" in vt else {}
    lengths = traj["vtype"].map(length_of) if "vtype" in traj else pd.Series(np.nan, traj.index)
    if lengths.isna().any() and not required:
        return None
    if lengths.isna().any():
        missing = sorted(set(traj["vtype"][lengths.isna()])) if "vtype" in traj else ["vtype"]
        raise UserError(
            f"{truth.folder}: vtypes.csv: length_m of vType {missing[0]} unknown: "
            "policy.observation with the own length or the gap needs every recorded vType's "
            "length (> 0 m)"
        )
    return lengths


def idm_action(params: Callable[[object], IdmParams], veh_length_m: float) -> ActionFn:
    """An IDM driving the core's hidden vehicles, its parameters ``params(core)``."""

    def act(core, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return idm_policy_accel(obs[core.hidden], params(core), veh_length_m)

    return act


@dataclass(frozen=True)
class OutOfSample:
    """Held-out pairs scored with taus fitted on other pairs of their drivers
    (``evaluation.driver_follow.out_of_sample_taus``): ``later`` (N,) bool, the pairs of
    each driver's second half; by agent, each of those pairs' tau [s] (fitted on its
    driver's first half, else the deployment's draw) and whether it is a fitted one."""

    later: np.ndarray
    taus: dict[str, np.ndarray]
    own: dict[str, np.ndarray]


# micro_consistency.csv's driver_tau column (only where a policy carries the drivers' taus):
# each driver's own tau fitted on the scored pairs themselves, on other pairs of the
# driver (its first half; the row scores the second half), or the prior's one tau.
IN_SAMPLE, OUT_OF_SAMPLE, ONE_TAU = "in_sample", "out_of_sample", "one"
OUT_OF_SAMPLE_SUFFIX = "_tau_out_of_sample"
# The IDMs' rows on the out-of-sample rows' pairs (each driver's second half): the rows that
# compare with those, where the IDMs' own rows score every held-out pair.
SECOND_HALF_SUFFIX = "_second_half"


def micro_consistency(
    agents: dict,
    idms: dict[str, IdmParams],
    obs: np.ndarray,
    accel: np.ndarray,
    sc,
    veh_length_m: float,
    taus: Mapping[str, np.ndarray | None] | None = None,
    out_of_sample: OutOfSample | None = None,
) -> pd.DataFrame:
    """Held-out observed actions: NLL under each learned policy, action RMSE for every method;
    ``veh_length_m``: the leader length IDM subtracts; ``taus``: by policy, each pair's
    driver's tau as its observations' trailing column (``policy.driver_follow``,
    ``evaluation.driver_follow.held_out_taus``: fitted on these pairs, in-sample); none: the
    prior's one tau. ``out_of_sample``: a row more for each policy it has taus for, named
    ``<policy>_tau_out_of_sample``, on the second half of each driver's pairs with taus
    fitted on the first half, and with it a row more for each IDM on those pairs
    (``<idm>_second_half``). Where a policy carries taus a ``driver_tau`` column says
    which (``IN_SAMPLE``, ``OUT_OF_SAMPLE``, ``ONE_TAU``; empty for the IDMs)."""
    a_min, a_max = sc.bounds.accel_mps2
    u = np.clip(accel, a_min, a_max)
    rows = []

    def score(name: str, o: np.ndarray, u: np.ndarray, agent, tau_kind: str) -> dict:
        with torch.no_grad():
            d = agent.dist(torch.as_tensor(o, dtype=torch.float32))
            nll = float(-d.log_prob(torch.as_tensor(u, dtype=torch.float32)).mean())
            rmse = float(np.sqrt(np.mean((np.clip(d.mean.numpy(), a_min, a_max) - u) ** 2)))
        return {"method": name, "nll": nll, "action_rmse_mps2": rmse, "n_pairs": len(u),
                "driver_tau": tau_kind}  # fmt: skip

    second = False  # an out-of-sample row written: the IDMs on its pairs too
    for name, agent in agents.items():
        own = (taus or {}).get(name)
        o = obs if own is None else with_tau(obs, own)
        rows.append(score(name, o, u, agent, ONE_TAU if own is None else IN_SAMPLE))
        later = None if out_of_sample is None else out_of_sample.taus.get(name)
        if later is not None:
            m = out_of_sample.later
            o = with_tau(obs[m], later)
            rows.append(score(name + OUT_OF_SAMPLE_SUFFIX, o, u[m], agent, OUT_OF_SAMPLE))
            second = True
    for name, p in idms.items():
        pred = np.clip(idm_policy_accel(obs, p, veh_length_m), a_min, a_max)
        halves = [(name, np.ones(len(u), dtype=bool))]
        if second:
            halves.append((name + SECOND_HALF_SUFFIX, out_of_sample.later))
        for label, m in halves:
            rows.append(
                {
                    "method": label,
                    "nll": np.nan,
                    "action_rmse_mps2": float(np.sqrt(np.mean((pred[m] - u[m]) ** 2))),
                    "n_pairs": int(m.sum()),
                    "driver_tau": "",
                }
            )
    table = pd.DataFrame(rows)
    if not any(t is not None for t in (taus or {}).values()):
        table = table.drop(columns="driver_tau")  # no policy carries taus: as before
    return table

"""What the leader-follower tests share: the tables' columns, a seeded random policy as the
follower under test, the tests on a ring file's section (``on_ring``), and the checks every
leader-follower run must pass (the leader replays its profile; the IDM followers are safe and
the reference follows itself)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.evaluation import leader_follower as lf
from macromicro_sumo.evaluation import leader_follower_section as lfs
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.inputs import scenario_inputs

TRACE_COLUMNS = [
    "scenario",
    "method",
    "trial",
    "time_s",
    "leader_speed_mps",
    "follower_speed_mps",
    "idm_follower_speed_mps",
    "gap_m",
]
SUMMARY_COLUMNS = ["scenario", "method", "trial", "rmse_vs_idm_mps", "min_gap_m", "collision"]


def on_ring(
    sc, followers, idm_params, n_trials: int, seed: int, profile: lf.LeaderProfile | None = None
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(traces, summary) of the tests on a ring file's closed one-lane section, the profile
    moved to its upper speed limit and mean spacing L / N (the evaluation's call)."""
    net = scenario_inputs(sc).net_file
    section = read_section(net, list(sc.section.edges), sc.section.closed)
    res = lfs.run_leader_follower_for(
        sc,
        section,
        net,
        followers,
        idm_params,
        section.length_m / sc.fleet.n_vehicles,
        sc.fleet.length_m,
        n_trials,
        seed,
        profile,
    )
    assert not res.skipped, res.message
    return res.traces, res.summary


def random_agent(observation: str, seed: int = 0) -> Agent:
    """An untrained agent, its weights drawn from ``torch.manual_seed(seed)``."""
    torch.manual_seed(seed)
    return Agent(observation=observation)


def random_policy(observation: str, seed: int = 0) -> dict[str, lf.Follower]:
    """``{"policy": ...}``: the stochastic follower of a ``random_agent``."""
    return {"policy": lf.policy_follower(random_agent(observation, seed))}


def rows(traces: pd.DataFrame, scenario: str, method: str) -> pd.DataFrame:
    """One scenario's trace rows of one method (every trial)."""
    return traces[(traces["scenario"] == scenario) & (traces["method"] == method)]


def assert_leader_replays(
    traces: pd.DataFrame, profile: lf.LeaderProfile, dt_s: float, atol: float = 0.0
) -> None:
    """In both scenarios the leader drives its profile, step for step (to ``atol`` m/s)."""
    for scenario in lf.SCENARIOS:
        lead = lf.leader_speeds(scenario, profile, dt_s)
        got = rows(traces, scenario, "IDM")["leader_speed_mps"]
        np.testing.assert_allclose(got, lead, rtol=0, atol=atol, err_msg=scenario)


def assert_idm_followers_safe(
    summary: pd.DataFrame, same_as_reference: tuple[str, ...], min_gap_m: float | None = None
) -> None:
    """The reference IDM and the followers that are the same IDM (``same_as_reference``)
    never collide, keep more than ``min_gap_m`` where given, and follow like the reference
    (RMSE 0)."""
    idm = summary[summary["method"].isin(["IDM", *same_as_reference])]
    assert set(idm["method"]) == {"IDM", *same_as_reference}
    assert not idm["collision"].any()
    if min_gap_m is not None:
        assert (idm["min_gap_m"] > min_gap_m).all()
    assert (idm["rmse_vs_idm_mps"] == 0).all()

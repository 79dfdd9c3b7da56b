"""Merges under speed commands (``deploy.merge``): SUMO's lane changer asks for speeds (a
merging vehicle adapts to its target lane, a follower there slows to open a gap) that a
speed command overrides. With ``merge = "sumo"`` a driven vehicle that must leave its lane
merges with SUMO's own model and driven followers on the target lane take SUMO's
cooperative slow-down: the acceleration lane drains as in the ground truth."""

from __future__ import annotations

import dataclasses

import pandas as pd
import pytest
from deploy_nets import idm_agent, merge_scenario

from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.deploy.run import DeployResult, Drive, load_context, run_method
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section

B = 1  # edge index of the merge edge B (lane 0: the acceleration lane)


@pytest.fixture(scope="module")
def dense_merge(tmp_path_factory: pytest.TempPathFactory) -> dict[str, DeployResult]:
    """The merge (2,400 + 700 veh/h) deployed with an IDM-like policy, merge none, handover
    and sumo, and the oracle: one held-out run, 60 s warm-up + 150 s, trajectories
    throughout."""
    folder = tmp_path_factory.mktemp("dense_merge")
    path = merge_scenario(
        folder,
        {"warmup_s": 60.0, "duration_s": 150.0, "n_runs": 2},
        main_vph=2400.0,
        ramp_vph=700.0,
        policy={"observation": "lookahead"},
        deploy={"fcd_s": 1e5},
    )
    sc = load_scenario(path)
    gt = simulate_section(sc, folder / "gt", progress=False)
    act = policy_batch(idm_agent(sc.policy.observation, 30.0))
    out = {}
    for name, merge, drive in [
        ("none", "none", Drive(act=act)),
        ("handover", "handover", Drive(act=act)),
        ("sumo", "sumo", Drive(act=act)),
        ("oracle", "sumo", Drive()),
    ]:
        sc_m = dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, merge=merge))
        out[name] = run_method(load_context(sc_m, gt), drive, folder / name)
    return out


def on_acceleration_lane(traj: pd.DataFrame) -> pd.DataFrame:
    return traj[(traj["edge_index"] == B) & (traj["lane_index"] == 0)]


def test_commands_override_the_merge_and_the_merge_option_restores_it(
    dense_merge: dict[str, DeployResult],
) -> None:
    """Commanded, ramp vehicles queue at the acceleration lane's end (SUMO alone: never);
    with merge = "sumo" the lane drains as SUMO's own drivers drain it (measured: 121
    vehicle-steps on it, oracle 88, merge none 718)."""
    stand = {
        k: int((on_acceleration_lane(r.trajectories)["speed_mps"] < 1.0).sum())
        for k, r in dense_merge.items()
    }
    steps = {k: len(on_acceleration_lane(r.trajectories)) for k, r in dense_merge.items()}
    assert stand["oracle"] == 0 and stand["none"] > 50, stand
    assert stand["sumo"] == 0, stand
    # Handing the merging vehicles over is not enough: commanded followers do not yield
    # (measured: 161 standing vehicle-steps against 250 without, 0 with the yield).
    assert stand["none"] > stand["handover"] > 0, stand
    assert steps["sumo"] < 0.5 * steps["none"], steps
    assert steps["sumo"] < 2.0 * steps["oracle"], steps
    for k in ("none", "handover", "sumo"):
        runs = dense_merge[k].runs.iloc[0]
        assert runs["collisions"] == 0 and runs["teleports"] == 0, (k, runs.to_dict())
        assert runs["vehicle_steps_driven"] > 5000, (k, runs.to_dict())


def test_a_driven_follower_yields_to_a_merging_vehicle(
    dense_merge: dict[str, DeployResult],
) -> None:
    """At a ramp vehicle's change from the acceleration lane into lane 1, the vehicle
    behind it there (a driven one) slowed by more than 1 m/s in the 4 s before: it opened
    the gap (measured: 6 of 21 merges; with merge = "none" 0 of 24)."""
    traj = dense_merge["sumo"].trajectories.sort_values(["vehicle_id", "time_s"])
    on_b = traj[traj["edge_index"] == B]
    prev = on_b.groupby("vehicle_id")["lane_index"].shift()
    merges = on_b[(prev == 0) & (on_b["lane_index"] == 1)]
    driven = traj[~traj["observed"]].set_index(["vehicle_id", "time_s"])["speed_mps"]
    yielded = 0
    for _, m in merges.iterrows():
        t = m["time_s"]
        lane1 = on_b[(on_b["time_s"] == t) & (on_b["lane_index"] == 1)]
        behind = lane1[lane1["arc_m"] < m["arc_m"]].sort_values("arc_m")
        if behind.empty or behind.iloc[-1]["observed"]:
            continue
        f = behind.iloc[-1]["vehicle_id"]
        speeds = driven.loc[f]
        window = speeds[(speeds.index >= t - 4.0) & (speeds.index <= t)]
        if len(window) > 2 and window.iloc[0] - window.min() > 1.0:
            yielded += 1
    assert len(merges) > 10, len(merges)
    assert yielded >= 3, (yielded, len(merges))

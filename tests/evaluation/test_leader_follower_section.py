"""Leader-follower tests (the paper's Fig. 3) on sections, through the section env core in
real SUMO: open and closed sections, the ring's figures on its section, skips."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT
from lf_trials import (
    TRACE_COLUMNS,
    assert_idm_followers_safe,
    assert_leader_replays,
    random_agent,
    random_policy,
    rows,
)

from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation import leader_follower as lf
from macromicro_sumo.evaluation import leader_follower_section as lfs
from macromicro_sumo.road.physics import leader_length_m
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs

# An IDM driver whose desired speed is the limit: it closes up on the leader within the test.
PARAMS = {
    "accel_mps2": 1.0,
    "decel_mps2": 1.5,
    "tau_s": 1.2,
    "min_gap_m": 2.0,
    "speed_factor": 1.0,
    "delta": 4.0,
}
LENGTH_M = 5.0


def road(name: str):
    sc = load_scenario(ROOT / "scenarios" / f"{name}.toml")
    net = scenario_inputs(sc).net_file
    return sc, read_section(net, list(sc.section.edges), sc.section.closed), net


# netgen_corridor: open, 1-3 lanes, lanes that end (an on-ramp's, lane drops); only one lane
# of each edge leads on to the end. ring_two_lane: closed, two lanes: SUMO's lane changing
# would take the follower past its leader.
@pytest.mark.parametrize(
    "name, lanes", [("netgen_corridor", [1, 0, 2, 0, 1, 2, 0]), ("ring_two_lane", [0, 0, 0, 0])]
)
def test_idm_follower_reaches_the_leaders_speed_with_a_safe_gap(name, lanes):
    sc, section, net = road(name)
    assert lfs.lane_path(section).tolist() == lanes
    profile = lf.LeaderProfile(duration_s=90.0, hold_s=10.0)
    # The length IDM subtracts from the leader column: none where it is the gap
    # (netgen_corridor's "lookahead_gap"), the vehicle's where it is the spacing.
    same = lf.idm_follower(PARAMS, leader_length_m(sc.policy.observation, LENGTH_M))
    res = lfs.run_leader_follower_for(
        sc, section, net, {"same_idm": same}, PARAMS, 30.0, LENGTH_M, 1, 0, profile
    )
    assert not res.skipped, res.message
    limit = float(np.nanmax(section.limits_mps[np.arange(len(lanes)), lanes]))
    moved = profile.moved(limit, 30.0)
    assert f"lanes {lanes}" in res.message and f"limit {limit:.2f} m/s" in res.message
    dt = sc.simulation.step_length_s
    tr = res.traces
    # The leader is commanded its profile: exact to rounding.
    assert_leader_replays(tr, moved, dt, atol=1e-9)
    for scenario in lf.SCENARIOS:
        d = rows(tr, scenario, "IDM")
        lead = lf.leader_speeds(scenario, moved, dt)
        assert len(d) == len(lead) == 181
        v, gap = d["follower_speed_mps"].to_numpy(), d["gap_m"].to_numpy()
        assert gap[0] == pytest.approx(moved.spacing_m - LENGTH_M, abs=1e-6)
        assert abs(v[-1] - lead[-1]) < 0.15, (scenario, v[-1], lead[-1])
        assert gap.min() > PARAMS["min_gap_m"]
        # It ends near the IDM equilibrium gap (s0 + vT) / sqrt(1 - (v / v0)^4).
        v0 = PARAMS["speed_factor"] * limit
        s_eq = (PARAMS["min_gap_m"] + v[-1] * PARAMS["tau_s"]) / np.sqrt(1 - (v[-1] / v0) ** 4)
        assert gap[-1] == pytest.approx(s_eq, rel=0.05)
        if scenario == "decelerate":
            assert np.diff(v).min() < 0  # it braked
        # The ground-truth follower against itself: the same trace, RMSE 0.
        mine = rows(tr, scenario, "same_idm")
        np.testing.assert_array_equal(mine["follower_speed_mps"], d["follower_speed_mps"])
    assert_idm_followers_safe(res.summary, ("same_idm",))


def test_a_section_too_short_is_skipped_in_one_line():
    sc, section, net = road("highway_bremen")
    res = lfs.run_leader_follower_for(sc, section, net, {}, PARAMS, 40.0, LENGTH_M, 1, 0)
    assert res.skipped and res.traces is None and res.summary is None
    assert res.message.startswith(f"{lfs.SKIPPED} (") and "\n" not in res.message
    assert "the section is 1875 m long; the test needs 2365 m" in res.message
    # A loop too short for the start spacing.
    sc, section, net = road("ring_paper_section")
    res = lfs.run_leader_follower_for(sc, section, net, {}, PARAMS, 700.0, LENGTH_M, 1, 0)
    assert res.skipped and "does not fit two 5 m vehicles on the 628.3 m loop" in res.message


def test_other_skips_and_bad_arguments():
    sc, section, net = road("ring_paper_section")
    steep = lf.LeaderProfile(ramp_mps2=0.8)
    res = lfs.run_leader_follower_for(sc, section, net, {}, PARAMS, 125.0, 5.0, 1, 0, steep)
    assert (
        res.skipped and "outside the action bounds bounds.accel_mps2 = [-1.1, 0.5]" in res.message
    )
    dead = replace(section, lane_ends=np.ones_like(section.lane_ends))
    assert lfs.lane_path(dead) is None
    res = lfs.run_leader_follower_for(sc, dead, net, {}, PARAMS, 125.0, 5.0, 1, 0)
    assert res.skipped and "no lane of the first edge" in res.message
    with pytest.raises(UserError, match="reserved"):
        lfs.run_leader_follower_for(
            sc, section, net, {"IDM": lf.idm_follower(PARAMS, 5.0)}, PARAMS, 125.0, 5.0, 1, 0
        )
    with pytest.raises(UserError, match="n_trials"):
        lfs.run_leader_follower_for(sc, section, net, {}, PARAMS, 125.0, 5.0, 0, 0)


def test_a_follower_that_loses_its_leader_is_skipped(monkeypatch):
    """With SUMO's own lane changing (mode 1621) a random policy overtakes its leader on the
    two-lane loop: the test says so in one line instead of comparing against nothing."""
    sc, section, net = road("ring_two_lane")
    monkeypatch.setattr(lfs, "NO_LANE_CHANGE", 1621)
    followers = random_policy(sc.policy.observation)
    profile = lf.LeaderProfile(duration_s=90.0, hold_s=10.0)
    res = lfs.run_leader_follower_for(sc, section, net, followers, PARAMS, 30.0, 5.0, 3, 0, profile)
    assert res.skipped and "\n" not in res.message
    # (78 s: a leader 250 m or more ahead is no leader in its observation, as deployed)
    assert res.message.endswith(
        "the follower lost its leader at t = 78 s (it sees no vehicle ahead)"
    )


# --------------------------------------------------------------------------- the stage's call


def test_section_stage_call_on_a_simulated_corridor(field_truth):
    """What the section evaluation calls: on a corridor whose vehicles are SUMO's IDM and
    Krauss cars (no [fleet]) the reference is IDM fitted to every recorded vehicle, the
    spacing the trajectories' mean, and the CSVs have the ring's columns."""
    from macromicro_sumo.env.section_bank import typical_length, typical_vclass
    from macromicro_sumo.evaluation.idm_fit import calibrate_idm
    from macromicro_sumo.evaluation.micro_data import micro_pairs
    from macromicro_sumo.road.leaders import section_leaders
    from macromicro_sumo.truth.section import load_section_truth

    sc = load_scenario(field_truth.parent / "corridor.toml")
    sc = replace(sc, evaluation=replace(sc.evaluation, lf_trials=2))
    truth = load_section_truth(field_truth, sc)
    length = typical_length(truth)
    # The thinned mean spacing against every scene's.
    traj = truth.trajectories
    every = []
    for _, g in traj.groupby(["run", "time_s"]):
        lead, gap = section_leaders(
            truth.section, g["lane_index"].to_numpy(), g["arc_m"].to_numpy()
        )
        every.append(gap[lead >= 0])
    assert lfs.truth_mean_spacing(sc, truth) == pytest.approx(
        np.concatenate(every).mean(), rel=0.03
    )
    obs, acc = micro_pairs(sc, truth, truth.runs)  # the observed vehicles only
    cal, _ = calibrate_idm(obs, acc, length)
    params, what = lfs.reference_idm(sc, truth, length)
    assert what.startswith("IDM fitted to every recorded vehicle of the ground truth (")
    assert params != {k: float(v) for k, v in cal.as_dict().items()}
    agents = {"policy": random_agent(sc.policy.observation)}
    res = lfs.section_leader_follower_tests(
        sc, truth, scenario_inputs(sc).net_file, agents, cal, length, typical_vclass(truth)
    )
    assert not res.skipped, res.message
    assert res.reference == what and res.message.endswith(f"reference: {what}")
    assert list(res.traces.columns) == TRACE_COLUMNS
    s = res.summary
    assert s.groupby("method").size().to_dict() == {"IDM": 2, "idm_calibrated": 4, "policy": 4}
    assert (s.loc[s["method"] == "IDM", "rmse_vs_idm_mps"] == 0).all()
    # The observed vehicles' IDM is not the population's: a finite, non-zero error.
    cal_rmse = s.loc[s["method"] == "idm_calibrated", "rmse_vs_idm_mps"]
    assert np.isfinite(cal_rmse).all() and cal_rmse.gt(0).all()


def test_fleet_sections_use_the_fleets_idm_and_L_over_N():
    from types import SimpleNamespace

    sc, section, _ = road("ring_paper_section")
    params, what = lfs.reference_idm(sc, None, LENGTH_M)  # a fleet needs no fit
    assert params == lf.mean_idm_params(sc) and "the fleet's IDM" in what
    truth = SimpleNamespace(section=section)
    assert lfs.truth_mean_spacing(sc, truth) == pytest.approx(2 * np.pi * 100 / 5, abs=1e-5)


def test_field_data_spacing_is_the_measured_leaders_else_the_stations():
    """Field data holds only the observed vehicles: the gap to the next of them is no
    spacing. Their measured leaders where the layout has them, else the stations' 1 / k."""
    from types import SimpleNamespace

    sc = SimpleNamespace(fleet=None, data=SimpleNamespace(source="files"))
    traj = pd.DataFrame({"leader_spacing_m": [np.nan, 30.0, 50.0], "arc_m": [0.0, 1.0, 2.0]})
    macro = pd.DataFrame({"mean_spacing_m": [80.0, 100.0]})
    truth = SimpleNamespace(trajectories=traj, macro=macro)
    assert lfs.truth_mean_spacing(sc, truth) == 40.0
    truth = SimpleNamespace(trajectories=traj.drop(columns="leader_spacing_m"), macro=macro)
    assert lfs.truth_mean_spacing(sc, truth) == 90.0

"""Leader-follower tests (the paper's Fig. 3) in real SUMO on the paper ring (its closed one-lane
section): IDM physics, profiles, seeding."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from conftest import PAPER_SCENARIO, ROOT
from lf_trials import (
    SUMMARY_COLUMNS,
    TRACE_COLUMNS,
    assert_idm_followers_safe,
    assert_leader_replays,
    on_ring,
    random_agent,
    random_policy,
    rows,
)

from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation import leader_follower as lf
from macromicro_sumo.road.physics import idm_accel
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs


@pytest.fixture(scope="module")
def sc():
    return load_scenario(PAPER_SCENARIO)


def numpy_follower(
    sc, lead_mps: np.ndarray, params: dict, spacing_m: float, limit_mps: float
) -> tuple[np.ndarray, np.ndarray]:
    """Reference: Euler IDM follower behind a replayed leader, action bounds as the env.

    v' = max(0, v + clip(a) dt), x' = x + v' dt for both vehicles. Returns (speed, gap).
    """
    dt = sc.simulation.step_length_s
    a_min, a_max = sc.bounds.accel_mps2
    length = sc.fleet.length_m
    x_l, x_f, v = spacing_m, 0.0, lead_mps[0]
    speed, gap = [v], [x_l - x_f - length]
    for t in range(len(lead_mps) - 1):
        a = idm_accel(
            v,
            x_l - x_f - length,
            v - lead_mps[t],
            params["speed_factor"] * limit_mps,
            params["tau_s"],
            params["accel_mps2"],
            params["decel_mps2"],
            params["min_gap_m"],
            params["delta"],
        )
        v = max(0.0, v + float(np.clip(a, a_min, a_max)) * dt)
        x_f += v * dt
        x_l += lead_mps[t + 1] * dt
        speed.append(v)
        gap.append(x_l - x_f - length)
    return np.array(speed), np.array(gap)


# The paper's start (126 m: IDM is almost free-road) and a close start where the IDM
# interaction term decides (braking behind the decelerating leader).
@pytest.mark.parametrize("spacing_m", [126.0, 30.0])
def test_idm_follower_in_sumo_matches_numpy_euler(sc, spacing_m):
    profile = lf.LeaderProfile(spacing_m=spacing_m)
    params = lf.mean_idm_params(sc)
    limit = sc.speed_limits.range_mps[1]
    traces, summary = on_ring(sc, {}, params, 1, seed=0, profile=profile)
    assert set(traces["method"]) == {"IDM"}
    for scenario in lf.SCENARIOS:
        d = traces[traces["scenario"] == scenario]
        lead = lf.leader_speeds(scenario, profile, sc.simulation.step_length_s)
        speed, gap = numpy_follower(sc, lead, params, spacing_m, limit)
        assert len(d) == len(lead) == profile.horizon(sc.simulation.step_length_s) + 1
        np.testing.assert_allclose(d["follower_speed_mps"], speed, rtol=0, atol=1e-6)
        np.testing.assert_allclose(d["gap_m"], gap, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(d["idm_follower_speed_mps"], d["follower_speed_mps"])
    assert_idm_followers_safe(summary, ())


def test_close_start_idm_settles_behind_slow_leader(sc):
    """IDM physics: 30 m behind a leader that slows to 11 m/s, the follower brakes, keeps
    at least s0 and approaches the IDM equilibrium gap (s0 + vT) / sqrt(1 - (v/v0)^4)."""
    params = lf.mean_idm_params(sc)
    profile = lf.LeaderProfile(spacing_m=30.0, duration_s=120.0)
    traces, summary = on_ring(sc, {}, params, 1, seed=0, profile=profile)
    d = traces[traces["scenario"] == "decelerate"]
    v0 = params["speed_factor"] * sc.speed_limits.range_mps[1]
    s_eq = (params["min_gap_m"] + 11.0 * params["tau_s"]) / np.sqrt(1 - (11.0 / v0) ** 4)
    assert d["follower_speed_mps"].iloc[-1] == pytest.approx(11.0, abs=0.05)
    assert d["gap_m"].iloc[-1] == pytest.approx(s_eq, abs=0.5)
    assert d["gap_m"].min() > params["min_gap_m"]
    assert d["follower_speed_mps"].diff().min() < -0.2 * sc.simulation.step_length_s
    assert not summary["collision"].any()


def test_accelerate_leader_replays_profile_and_idm_ends_near_13(sc):
    profile = lf.LeaderProfile()
    traces, summary = on_ring(sc, {}, lf.mean_idm_params(sc), 1, seed=0)
    d = traces[traces["scenario"] == "accelerate"]
    lead = lf.leader_speeds("accelerate", profile, sc.simulation.step_length_s)
    np.testing.assert_array_equal(d["leader_speed_mps"].to_numpy(), lead)
    assert lead[0] == 11.0 and lead[-1] == 13.0
    assert np.all(np.diff(lead) <= profile.ramp_mps2 * sc.simulation.step_length_s + 1e-12)
    np.testing.assert_allclose(d["time_s"], np.arange(len(lead)) * 0.5)
    assert d["follower_speed_mps"].iloc[0] == 11.0
    assert d["follower_speed_mps"].iloc[-1] == pytest.approx(13.0, abs=0.25)
    assert d["gap_m"].iloc[0] == pytest.approx(126.0 - sc.fleet.length_m)
    assert not summary["collision"].any()
    assert (summary["min_gap_m"] > lf.mean_idm_params(sc)["min_gap_m"]).all()


def test_leader_profiles():
    p = lf.LeaderProfile()
    up = lf.leader_speeds("accelerate", p, 0.5)
    down = lf.leader_speeds("decelerate", p, 0.5)
    assert len(up) == 121
    t = np.arange(121) * 0.5
    np.testing.assert_allclose(up[t <= 20], 11.0)
    np.testing.assert_allclose(up[t >= 30], 13.0)
    np.testing.assert_allclose(up[(t > 20) & (t < 30)], 11.0 + 0.2 * (t[(t > 20) & (t < 30)] - 20))
    np.testing.assert_allclose(up + down, 24.0)
    with pytest.raises(UserError, match="multiple"):
        lf.LeaderProfile(duration_s=10.2).horizon(0.5)
    with pytest.raises(UserError, match="scenario"):
        lf.leader_speeds("cruise", p, 0.5)


def test_bad_arguments(sc):
    params = lf.mean_idm_params(sc)
    with pytest.raises(UserError, match="reserved"):
        on_ring(sc, {"IDM": lf.idm_follower(params, 5.0)}, params, 1, 0)
    with pytest.raises(UserError, match="n_trials"):
        on_ring(sc, {}, params, 0, 0)
    with pytest.raises(UserError, match="tau_s"):
        lf.idm_follower({k: v for k, v in params.items() if k != "tau_s"}, 5.0)


@pytest.fixture(scope="module")
def random_agent_runs(sc):
    """A random-weights agent, 3 stochastic trials, twice with seed 7 and once with seed 8."""
    agent = random_agent(sc.policy.observation)
    followers = {
        "policy": lf.policy_follower(agent),
        "policy_mean": lf.policy_follower(agent, False),
    }
    profile = lf.LeaderProfile(duration_s=20.0, hold_s=5.0)
    params = lf.mean_idm_params(sc)
    run = lambda seed: on_ring(sc, followers, params, 3, seed, profile)  # noqa: E731
    return run(7), run(7), run(8)


def test_policy_traces_are_seeded(random_agent_runs):
    (tr_a, sm_a), (tr_b, sm_b), (tr_c, _) = random_agent_runs
    pd.testing.assert_frame_equal(tr_a, tr_b)
    pd.testing.assert_frame_equal(sm_a, sm_b)
    pol = tr_a[(tr_a["method"] == "policy") & (tr_a["scenario"] == "accelerate")]
    speeds = [g["follower_speed_mps"].to_numpy() for _, g in pol.groupby("trial")]
    assert len(speeds) == 3
    assert not np.allclose(speeds[0], speeds[1])
    assert not np.allclose(speeds[1], speeds[2])
    other = tr_c[(tr_c["method"] == "policy") & (tr_c["scenario"] == "accelerate")]
    assert not np.allclose(speeds[0], other[other["trial"] == 0]["follower_speed_mps"])
    # The mean action is deterministic: every trial and seed gives the same trace.
    for tr in (tr_a, tr_c):
        det = tr[tr["method"] == "policy_mean"]
        for _, g in det.groupby("scenario"):
            by_trial = g.pivot(index="time_s", columns="trial", values="follower_speed_mps")
            np.testing.assert_array_equal(by_trial.to_numpy(), by_trial[[0]].to_numpy()[:, [0] * 3])


def test_trace_table_and_summary(random_agent_runs):
    traces, summary = random_agent_runs[0]
    assert list(traces.columns) == TRACE_COLUMNS
    assert list(summary.columns) == SUMMARY_COLUMNS
    assert len(summary) == 2 * (1 + 3 + 3)
    assert traces.groupby(["scenario", "method", "trial"]).size().eq(41).all()
    for (scenario, method, trial), g in traces.groupby(["scenario", "method", "trial"]):
        idm = traces[(traces["scenario"] == scenario) & (traces["method"] == "IDM")]
        ref = idm["follower_speed_mps"].to_numpy()
        np.testing.assert_array_equal(g["idm_follower_speed_mps"], ref[: len(g)])
        v = g["follower_speed_mps"].to_numpy()
        expected = np.sqrt(np.mean((v[1:] - ref[1 : len(v)]) ** 2))
        row = summary[
            (summary["scenario"] == scenario)
            & (summary["method"] == method)
            & (summary["trial"] == trial)
        ].iloc[0]
        assert row["rmse_vs_idm_mps"] == pytest.approx(expected, rel=1e-12, abs=1e-15)
        assert row["min_gap_m"] == g["gap_m"].min()
        assert row["collision"] == (g["gap_m"] < 0).any()
    assert summary.loc[summary["method"] == "policy", "rmse_vs_idm_mps"].gt(0).all()
    table = lf.method_summary(summary)
    assert len(table) == 6
    pol = table[(table["method"] == "policy") & (table["scenario"] == "decelerate")].iloc[0]
    assert pol["trials"] == 3
    sel = summary[(summary["method"] == "policy") & (summary["scenario"] == "decelerate")]
    assert pol["mean_rmse_vs_idm_mps"] == pytest.approx(sel["rmse_vs_idm_mps"].mean())


# --------------------------------------------------------------------------- other rings

SUGIYAMA_SCENARIO = ROOT / "scenarios" / "ring_sugiyama.toml"


def test_paper_ring_keeps_the_paper_profile(sc):
    paper = (sc.speed_limits.range_mps[1], 2 * np.pi * 100.0 / sc.fleet.n_vehicles)
    assert lf.LeaderProfile().moved(*paper) == lf.LeaderProfile()
    custom = lf.LeaderProfile(spacing_m=30.0, duration_s=20.0, hold_s=5.0)
    assert custom.moved(*paper) == custom


def test_leader_follower_on_a_sugiyama_ring():
    """A 230 m ring with 22 vehicles (limits up to 10 m/s): the test, moved to the ring,
    runs for a learned policy and the IDM followers without error. Unscaled, the leader
    (11 -> 13 m/s, above the followers' desired speed) came round the ring into the IDM
    follower, and a follower that outlived that reference ended in a ValueError."""
    sc = load_scenario(SUGIYAMA_SCENARIO)
    assert sc.fleet.n_vehicles == 22
    params = lf.mean_idm_params(sc)
    followers = {
        **random_policy(sc.policy.observation),
        "idm_calibrated": lf.idm_follower(params, sc.fleet.length_m),
    }
    profile = lf.LeaderProfile(duration_s=30.0, hold_s=10.0)
    traces, summary = on_ring(sc, followers, params, 2, sc.seed, profile)
    net = scenario_inputs(sc).net_file
    length = read_section(net, list(sc.section.edges), sc.section.closed).length_m
    assert length == pytest.approx(230.0, abs=0.1)
    mean_spacing = length / sc.fleet.n_vehicles
    moved = profile.moved(sc.speed_limits.range_mps[1], mean_spacing)
    assert moved.spacing_m == pytest.approx(126.0 * mean_spacing / (2 * np.pi * 100 / 5))
    assert moved.low_speed_mps == pytest.approx(11.0 * 10.0 / 14.0)
    assert moved.high_speed_mps == pytest.approx(13.0 * 10.0 / 14.0)
    assert len(summary) == 2 * (1 + 2 + 2)
    dt = sc.simulation.step_length_s
    assert_leader_replays(traces, moved, dt)
    for scenario in lf.SCENARIOS:
        d = rows(traces, scenario, "IDM")
        assert d["gap_m"].iloc[0] == pytest.approx(moved.spacing_m - sc.fleet.length_m)
        assert d["follower_speed_mps"].max() <= params["speed_factor"] * 10.0 + 1e-9
    # The IDM followers follow the leader without touching it, and are never run into.
    assert_idm_followers_safe(summary, ("idm_calibrated",), params["min_gap_m"])
    assert traces.groupby(["scenario", "method", "trial"]).size().le(profile.horizon(dt) + 1).all()


def test_trial_that_outlives_the_reference(sc):
    """A reference follower that crashes ends before the trials: their later steps have no
    reference speed (NaN) and their RMSE covers the steps both have."""
    # Braking late (T = 0.1 s, s0 = 0, a = b = 10 m/s^2) with the actuator's a_min: it crashes.
    reckless = lf.mean_idm_params(sc) | {
        "accel_mps2": 10.0,
        "decel_mps2": 10.0,
        "tau_s": 0.1,
        "min_gap_m": 0.0,
        "speed_factor": 2.0,
    }
    careful = lf.idm_follower(lf.mean_idm_params(sc), sc.fleet.length_m)
    profile = lf.LeaderProfile(spacing_m=30.0, duration_s=30.0, hold_s=5.0)
    traces, summary = on_ring(sc, {"careful": careful}, reckless, 1, 0, profile)
    for scenario in lf.SCENARIOS:
        d = traces[traces["scenario"] == scenario]
        ref = d[d["method"] == "IDM"]
        mine = d[d["method"] == "careful"]
        assert summary.set_index(["scenario", "method"]).loc[(scenario, "IDM"), "collision"]
        assert len(ref) < len(mine) == profile.horizon(sc.simulation.step_length_s) + 1
        ref_col = mine["idm_follower_speed_mps"].to_numpy()
        np.testing.assert_array_equal(ref_col[: len(ref)], ref["follower_speed_mps"])
        assert np.isnan(ref_col[len(ref) :]).all()
        v, r = mine["follower_speed_mps"].to_numpy(), ref["follower_speed_mps"].to_numpy()
        got = summary.set_index(["scenario", "method"]).loc[
            (scenario, "careful"), "rmse_vs_idm_mps"
        ]
        n = len(r)
        assert got == pytest.approx(np.sqrt(np.mean((v[1:n] - r[1:n]) ** 2)), rel=1e-12)
    assert lf.rmse_vs_reference(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.5])) == 0.5

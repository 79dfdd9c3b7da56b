"""Per-run speed limits on a section (issue 16, item 4): where the ground truth drew each
run's limits (``[speed_limits]``, ``speed_limits.csv``), Stage II's episodes, observations,
SUMO's lanes, psi's speed bounds and the demand episodes read the run's limits; every other
section keeps the network's. Real SUMO on the paper's ring read as a section."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT, dump_toml

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import merge_scenario  # noqa: E402

from macromicro_sumo.data.section import psi_table, run_limits_mps, section_snapshots  # noqa: E402
from macromicro_sumo.deploy.run import load_context  # noqa: E402
from macromicro_sumo.env.demand import DemandCore  # noqa: E402
from macromicro_sumo.env.section import SectionCore  # noqa: E402
from macromicro_sumo.env.section_bank import build_section_bank  # noqa: E402
from macromicro_sumo.env.section_envs import true_section_completion  # noqa: E402
from macromicro_sumo.errors import UserError  # noqa: E402
from macromicro_sumo.evaluation.micro_data import micro_pairs  # noqa: E402
from macromicro_sumo.road.physics import idm_accel  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.sumo.inputs import scenario_inputs  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402

SCENARIO = ROOT / "scenarios" / "ring_paper_section.toml"
NETWORK_LIMIT_MPS = 13.89  # the ring network's own limit on every edge


@pytest.fixture(scope="module")
def ring(tmp_path_factory: pytest.TempPathFactory):
    """ring_paper_section, small: 3 runs of 60 s (a few seconds of SUMO)."""
    folder = tmp_path_factory.mktemp("ring_limits")
    table = tomllib.loads(SCENARIO.read_text())
    net = table["network"]
    net["net_file"] = str((SCENARIO.parent / net["net_file"]).resolve())
    net["additional_files"] = [
        str((SCENARIO.parent / p).resolve()) for p in net["additional_files"]
    ]
    table["simulation"].update(n_runs=3, duration_s=60.0)
    table["detectors"]["interval_s"] = 30.0
    path = folder / "ring.toml"
    path.write_text(dump_toml(table))
    sc = load_scenario(path)
    out = simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(out, sc)


def csv_limits(truth) -> pd.DataFrame:
    """speed_limits.csv as run x edge (the section's edge order)."""
    df = pd.read_csv(truth.folder / "speed_limits.csv", dtype={"edge_id": str})
    return df.pivot(index="run", columns="edge_id", values="speed_limit_mps")[
        list(truth.section.edge_ids)
    ]


def test_episodes_observations_and_sumo_lanes_take_the_runs_limits(ring) -> None:
    sc, truth = ring
    lim = csv_limits(truth)
    # The draws differ from the network's limit and between runs: a reader of the network's
    # fixed limit, or of another run's, fails below.
    assert (np.abs(lim.to_numpy() - NETWORK_LIMIT_MPS) > 0.3).all()
    assert len({tuple(r) for r in lim.to_numpy()}) == len(lim)
    np.testing.assert_array_equal(run_limits_mps(truth, lim.index)[:, :, 0], lim.to_numpy())

    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_section_completion, 5, 0)
    np.testing.assert_array_equal(bank.limits_mps[:, :, 0], lim.loc[bank.run].to_numpy())

    sec = truth.section
    lane_ids = [ids[0] for ids in sec.edge_lane_ids]
    first = [int(np.flatnonzero(bank.run == r)[0]) for r in truth.runs]
    core = SectionCore(sc, sec, bank, scenario_inputs(sc).net_file, seed=0)
    try:
        for ep in first + first[::-1]:  # each run after another run's limits
            run_lim = lim.loc[int(bank.run[ep])].to_numpy()
            obs = core.reset(ep)
            np.testing.assert_allclose(core.sim.lane_speed_limits(lane_ids), run_lim)
            on = core.active
            e = sec.edge_index(core.arc[on])
            np.testing.assert_array_equal(obs[on, 1], run_lim[e])  # v_limit where it drives
            np.testing.assert_array_equal(obs[on, 4], run_lim[(e + 1) % 4])  # the next edge's
            for _ in range(5):
                res = core.step(np.zeros(int(bank.hidden[ep].sum())))
                assert not res.error and not res.collision
                on = res.active
                e = sec.edge_index(core.arc[on])
                np.testing.assert_array_equal(res.obs[on, 1], run_lim[e])
    finally:
        core.close()

    # psi's speed bounds are capped at 1.5 x the run's highest limit, not the network's.
    psi = psi_table(truth, sc)
    cap = 1.5 * lim.max(axis=1).loc[psi["run"]].to_numpy()
    assert (psi["speed_max_mps"].to_numpy() <= cap + 1e-9).all()

    with pytest.raises(UserError, match=r"speed_limits.csv: no limit .* run\(s\) \[99\]"):
        run_limits_mps(truth, np.array([99]))


def idm(obs: np.ndarray) -> np.ndarray:
    """IDM on the observation (the fleet's middle parameters, desired speed the limit)."""
    return idm_accel(obs[:, 0], obs[:, 2] - 5.0, obs[:, 3], obs[:, 1], 1.0, 1.5, 1.3, 2.5)


def test_demand_episodes_of_a_fleet_start_from_the_recorded_run(ring) -> None:
    """A fleet's demand episode is the truth's run: SUMO, given the run's draws, seed and
    limits, holds every vehicle where the trajectories have it at t0; the population (not
    instrumented) is driven from there at the run's limits, without collisions."""
    sc, truth = ring
    lim = csv_limits(truth)
    traj = truth.trajectories
    core = DemandCore(sc, truth, truth.runs, 20)
    try:
        assert all(
            t0 >= sc.simulation.step_length_s
            for _, t0 in core.windows(np.random.default_rng(0), 20)
        )
        for run, t0 in ((int(truth.runs[1]), 30.0), (int(truth.runs[0]), 12.5)):
            core.reset(run, t0)
            rec = traj[(traj["run"] == run) & (np.abs(traj["time_s"] - t0) < 1e-6)]
            states = core.lane_states()
            assert sorted(states) == sorted(rec["vehicle_id"])  # the whole fleet, no other
            arc = {v: truth.section.lanes[s[0]][2] + s[1] for v, s in states.items()}
            np.testing.assert_allclose(rec["arc_m"], rec["vehicle_id"].map(arc), atol=1e-4)
            speed = {v: s[2] for v, s in states.items()}
            np.testing.assert_allclose(rec["speed_mps"], rec["vehicle_id"].map(speed), atol=1e-4)
            vids, obs = core.observe()
            assert vids == sorted(rec.loc[~rec["observed"], "vehicle_id"]) and vids
            run_lim = lim.loc[run].to_numpy()
            e = truth.section.edge_index(np.array([arc[v] for v in vids]))
            np.testing.assert_array_equal(obs[:, 1], run_lim[e])
            np.testing.assert_array_equal(obs[:, 4], run_lim[(e + 1) % 4])
            for _ in range(20):
                vids, obs = core.observe()
                res = core.step(idm(obs))
                assert res.collisions == 0 and not res.left and 0.0 < res.r_macro <= 1.0
    finally:
        core.close()


@pytest.fixture(scope="module")
def merge(tmp_path_factory: pytest.TempPathFactory):
    """A section with the user's route files (an on-ramp merge): no per-run limits."""
    folder = tmp_path_factory.mktemp("limits_merge")
    path = merge_scenario(
        folder,
        {"warmup_s": 60.0, "duration_s": 60.0, "n_runs": 1},
        policy={"observation": "lookahead"},
    )
    sc = load_scenario(path)
    return sc, load_section_truth(simulate_section(sc, folder / "gt", progress=False), sc)


def test_other_sections_keep_the_networks_limits(merge) -> None:
    sc, truth = merge
    sec = truth.section
    assert not (truth.folder / "speed_limits.csv").exists()
    np.testing.assert_array_equal(run_limits_mps(truth, truth.runs)[0], sec.limits_mps)
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_section_completion, 5, 0)
    assert all(bank.section_of(sec, ep) is sec for ep in range(len(bank)))
    lane_ids = [lane for ids in sec.edge_lane_ids for lane in ids]
    core = SectionCore(sc, sec, bank, scenario_inputs(sc).net_file, seed=0)
    try:
        before = core.sim.lane_speed_limits(lane_ids)
        core.reset(len(bank) // 2)
        np.testing.assert_array_equal(core.sim.lane_speed_limits(lane_ids), before)
        assert core.episode_section is sec
    finally:
        core.close()
    np.testing.assert_array_equal(before, sec.limits_mps[~np.isnan(sec.limits_mps)])
    demand = DemandCore(sc, truth, truth.runs, 10)
    try:
        demand.reset(int(truth.runs[0]), 70.0)
        np.testing.assert_array_equal(demand.section.limits_mps, sec.limits_mps)
    finally:
        demand.close()


def test_micro_pairs_observe_the_runs_limits(ring) -> None:
    """The observed pairs that the likelihood, the IDM fit and the prior see carry each run's
    limits, as the env's observations do (not the network's 13.89 m/s)."""
    sc, truth = ring
    lim = csv_limits(truth)
    seen = set()
    for run in truth.runs:
        obs, _ = micro_pairs(sc, truth, np.array([run]))
        assert set(np.unique(obs[:, 1])) <= set(lim.loc[int(run)].to_numpy())
        seen |= set(np.unique(obs[:, 1]))
    assert len(seen) > 1 and NETWORK_LIMIT_MPS not in seen


def test_deployment_drivers_observe_the_runs_limits(ring) -> None:
    """A deployment re-runs held-out runs with their own limits in SUMO; its drivers observe
    the same limits (the Stage II env's), not the network's."""
    sc, truth = ring
    lim = csv_limits(truth)
    ctx = load_context(sc, truth.folder)
    assert ctx.held_out and set(ctx.run_sections) == set(truth.runs.tolist())
    for run, section in ctx.run_sections.items():
        np.testing.assert_array_equal(section.limits_mps[:, 0], lim.loc[run].to_numpy())

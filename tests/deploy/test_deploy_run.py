"""Deployments over whole runs on a small section with inflow, an on-ramp merge and lane
changes: the oracle is the ground truth, a policy drives it collision-free, the output
folders hold the ground truth's files; ``macromicro deploy`` refuses bad input in one line."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import dump_toml
from deploy_nets import idm_agent, merge_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.deploy.run import Drive, load_context, run_method
from macromicro_sumo.deploy.stage import deploy
from macromicro_sumo.evaluation.idm_fit import GippsParams, IdmParams
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.prior import idm_prior_params
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section


@pytest.fixture(scope="module")
def merge_truth(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(scenario file, ground truth) of the merge: 2 runs of 60 s warm-up + 120 s."""
    folder = tmp_path_factory.mktemp("deploy_merge")
    path = merge_scenario(
        folder,
        {"warmup_s": 60.0, "duration_s": 120.0, "n_runs": 2},
        policy={"observation": "lookahead"},
        deploy={"fcd_s": 30.0},
    )
    gt = simulate_section(load_scenario(path), folder / "gt", progress=False)
    return path, gt


def test_oracle_reproduces_the_ground_truths_detectors(
    merge_truth: tuple[Path, Path], tmp_path: Path
) -> None:
    path, gt = merge_truth
    sc = load_scenario(path)
    m = deploy(sc, gt, None, tmp_path / "dep", progress=False, methods=["oracle"])
    held = m["held_out_runs"]
    assert held and set(m["methods"]) == {"oracle"}
    out = tmp_path / "dep" / "oracle"
    for name in ("detectors.csv", "detector_passages.csv", "macro.csv"):
        truth = pd.read_csv(gt / name)
        truth = truth[truth["run"].isin(held)].reset_index(drop=True)
        got = pd.read_csv(out / name)
        assert len(got) >= 8, name  # 4 intervals x (detectors, trajectories) at least
        pd.testing.assert_frame_equal(got, truth, check_exact=True, obj=name)
    runs = pd.read_csv(out / "runs.csv")
    truth_runs = pd.read_csv(gt / "runs.csv")
    truth_runs = truth_runs[truth_runs["run"].isin(held)].reset_index(drop=True)
    pd.testing.assert_frame_equal(runs[truth_runs.columns], truth_runs)
    assert (runs["vehicle_steps_driven"] == 0).all()
    traj = pd.read_csv(out / "trajectories.csv")
    assert traj["time_s"].min() == 60.5 and traj["time_s"].max() < 60.5 + 30.0
    assert (out / "sumo" / f"run_{held[0]:03d}" / "e1.xml").is_file()
    assert json.loads((out / "manifest.json").read_text())["method"] == "oracle"


def test_policy_drives_the_merge_without_collisions(
    merge_truth: tuple[Path, Path], tmp_path: Path
) -> None:
    """Every non-instrumented vehicle on the section is driven by the policy, entering from
    upstream and the on-ramp, changing lanes where the acceleration lane ends."""
    path, gt = merge_truth
    sc = load_scenario(path)
    ctx = load_context(sc, gt)
    agent = idm_agent(sc.policy.observation, 30.0)
    res = run_method(ctx, Drive(act=policy_batch(agent)), tmp_path)
    runs = res.runs.iloc[0]
    assert runs["collisions"] == 0 and runs["teleports"] == 0, runs.to_dict()
    # 180 s at ~2,300 veh/h on 1.3 km: thousands of driven vehicle-steps, ramp ones too.
    assert runs["vehicle_steps_driven"] > 5000
    traj = res.trajectories
    ramp = traj[traj["vehicle_id"].str.startswith("r.") & ~traj["observed"]]
    assert ramp["lane_index"].nunique() >= 2  # ramp vehicles left the acceleration lane
    # The stream goes through: the last loops count what the first ones count, plus the ramp.
    det = res.detectors[res.detectors["begin_s"] >= 90.0]
    first, last = det["arc_m"].min(), det["arc_m"].max()
    n_first = det.loc[det["arc_m"] == first, "n_veh"].sum()
    n_last = det.loc[det["arc_m"] == last, "n_veh"].sum()
    assert n_first > 30 and n_last > n_first, (n_first, n_last)
    # The safety layer (the default) acted rarely for a policy that drives like IDM.
    assert runs["safety_acted"] < 0.05 * runs["vehicle_steps_driven"]


def test_policy_alone_also_avoids_collisions_at_the_merge(
    merge_truth: tuple[Path, Path], tmp_path: Path
) -> None:
    path, gt = merge_truth
    sc = load_scenario(path)
    sc = dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, safety="none"))
    ctx = load_context(sc, gt)
    res = run_method(ctx, Drive(act=policy_batch(idm_agent(sc.policy.observation, 30.0))), tmp_path)
    runs = res.runs.iloc[0]
    assert runs["collisions"] == 0 and runs["safety_acted"] == 0, runs.to_dict()


def test_deploy_without_a_policy_is_a_one_line_error(
    merge_truth: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    path, gt = merge_truth
    empty = tmp_path / "run" / "policy"
    empty.mkdir(parents=True)
    (tmp_path / "run" / "ground_truth").symlink_to(gt)
    rc = main(
        ["deploy", str(path), "--policy", str(tmp_path / "run"), "--out", str(tmp_path / "d")]
    )
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err
    assert err.startswith("error: ") and "policy.pt" in err and str(empty) in err
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize(
    ("prior", "bound"),
    [("none", np.inf), ("idm", np.inf), ("idm", 1.0), ("gipps", 1.0), ("gipps", 0.0)],
)
def test_the_deployed_action_is_the_policys_mean_action(prior: str, bound: float) -> None:
    """The numpy batch gives ``Agent.mean_action``: the actor's output, plus the fitted
    model's acceleration for a residual policy (``policy.prior`` idm or gipps), the
    residual bounded (or the prior alone: bound 0), to 1e-6 m/s^2 of the agent in float64
    and to float32's rounding of the agent as trained."""
    torch.manual_seed(0)
    idm = IdmParams(speed_factor=1.0, tau_s=1.2, accel_mps2=1.5, decel_mps2=2.0, min_gap_m=2.0)
    gipps = GippsParams(speed_factor=1.05, accel_mps2=2.0, decel_mps2=4.5, tau_s=1.1, min_gap_m=2.0)
    params = {
        "none": None,
        "idm": idm_prior_params(idm.as_dict(), 5.0),
        "gipps": {**gipps.as_dict(), "veh_length_m": 5.0, "dt_s": 0.5},
    }[prior]
    agent = Agent(
        16, observation="lookahead", prior=prior, prior_params=params, residual_bound_mps2=bound
    )
    with torch.no_grad():  # a residual starts at 0: give it a trained-looking output
        agent.actor[-1].weight.normal_(0.0, 1.0)
        agent.actor[-1].bias.fill_(0.3)
    rng = np.random.default_rng(0)
    obs = np.column_stack(
        [rng.uniform(0, 30, 300), np.full(300, 30.0), rng.uniform(5, 250, 300)]
        + [rng.uniform(-5, 5, 300), np.full(300, 30.0), rng.uniform(0, 500, 300)]
    )
    got = policy_batch(agent)(obs)
    with torch.no_grad():
        want32 = agent.mean_action(torch.as_tensor(obs, dtype=torch.float32)).numpy()
        want64 = agent.double().mean_action(torch.as_tensor(obs)).numpy()
    assert got.dtype == np.float64 and got.shape == (300,)
    np.testing.assert_allclose(got, want64, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got, want32, rtol=0, atol=1e-4)
    if prior != "none":  # the model's braking behind a close, slower leader is in there
        assert got.min() < -1.0


def test_a_vtype_switch_drives_the_cars_looping_on_a_closed_section(tmp_path: Path) -> None:
    """Spreewaldring (one-lane circuit, 31 cars kept looping by rerouters, section closed):
    SUMO's defaults drive the non-instrumented cars (vehicle_steps_driven > 0) and change
    the detectors against the oracle, which reproduces the ground truth."""
    root = Path(__file__).resolve().parents[2]
    table = tomllib.loads((root / "scenarios" / "spreewaldring.toml").read_text())
    table["network"]["sumocfg"] = str(
        root / "sumo_nets" / "spreewaldring" / "spreewaldring.sumocfg"
    )
    table["simulation"].update(warmup_s=60.0, duration_s=120.0, n_runs=2)
    table["detectors"]["interval_s"] = 30.0
    table["deploy"] = {"fcd_s": 30.0}
    path = tmp_path / "spreewald.toml"
    path.write_text(dump_toml(table))
    sc = load_scenario(path)
    gt = simulate_section(sc, tmp_path / "gt", progress=False)
    ctx = load_context(sc, gt)
    oracle = run_method(ctx, Drive(), tmp_path / "oracle")
    dflt = run_method(ctx, Drive(defaults=True), tmp_path / "defaults")
    assert (oracle.runs["vehicle_steps_driven"] == 0).all()
    assert (dflt.runs["vehicle_steps_driven"] > 0).all()
    # ~80% of the cars are driven from their start: most of their steps on the section.
    steps = (sc.simulation.warmup_s + sc.simulation.duration_s) / sc.simulation.step_length_s
    assert dflt.runs["vehicle_steps_driven"].min() > 0.5 * 0.8 * 31 * steps
    assert not dflt.detectors.equals(oracle.detectors)

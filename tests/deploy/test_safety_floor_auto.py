"""``deploy.safety_floor_on = "auto"`` (``deploy.floor_choice``): the floor chosen by
deploying each candidate on training runs and comparing the speed RMSE against the truth's
detectors there. Real SUMO, on a road whose ground-truth cars cruise at 4.5 m/s (speedFactor
0.15 of a 30 m/s limit), below the floor of "all" (a fifth of the limit, 6 m/s): a policy
that drives as the truth does is pushed to 6 m/s by "all" and left alone by "standing"; a
policy that always brakes moves at 6 m/s with "all" and crawls with "standing"."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import dump_toml, line_net, write_scenario

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.deploy import floor_choice
from macromicro_sumo.deploy.floor_choice import choose_floor, needs_choice, resolve_floor
from macromicro_sumo.deploy.run import DeployContext, Drive, load_context, run_method
from macromicro_sumo.deploy.stage import MANIFEST, SUMMARY, deploy, method_drive
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import read_manifest
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.checkpoint import CHECKPOINT_FORMAT, signature
from macromicro_sumo.report.deploy import deployment_section
from macromicro_sumo.report.deploy_manifest_lines import floor_choice_lines
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section

CRUISE_MPS = 4.5  # the truth's cars: 0.15 x 30 m/s, no dawdling, no speed deviation
SLOW = (
    '<vType id="slow" length="5" minGap="2.5" accel="2.6" decel="4.5" sigma="0" '
    'speedFactor="0.15" speedDev="0"/>'
)


def like_the_truth(obs: np.ndarray) -> np.ndarray:
    """To the truth's cruise speed within a step (the bounds clip it)."""
    return (CRUISE_MPS - obs[:, 0]) / 0.5


def always_brake(obs: np.ndarray) -> np.ndarray:
    return np.full(len(obs), -30.0)


@pytest.fixture(scope="module")
def slow_road(tmp_path_factory: pytest.TempPathFactory) -> tuple[DeployContext, Path]:
    """(deployment context, ground truth): one lane, 600 m, 600 veh/h of the slow cars,
    4 runs of 150 s (1 held out, 1 validation, 2 training), the floor chosen on 1 run."""
    folder = tmp_path_factory.mktemp("floor_auto")
    (folder / "net").mkdir()
    net = line_net(folder / "net", (300.0, 600.0), 1, 30.0)
    routes = folder / "slow.rou.xml"
    routes.write_text(
        f'<routes>\n    {SLOW}\n    <route id="r" edges="A B"/>\n'
        '    <flow id="f" type="slow" route="r" begin="0" end="3600" vehsPerHour="600" '
        'departSpeed="desired"/>\n</routes>\n'
    )
    table = {
        "name": "slow_road",
        "seed": 3,
        "network": {"kind": "sumo", "net_file": str(net), "route_files": [str(routes)]},
        "section": {"edges": ["A", "B"]},
        "instrumented": {"penetration": 0.2},
        "simulation": {"warmup_s": 0.0, "duration_s": 150.0, "n_runs": 4},
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 150.0},
        "deploy": {"safety_floor_on": "auto", "safety_floor_runs": 1},
    }
    path = folder / "slow_road.toml"
    path.write_text(dump_toml(table))
    sc = load_scenario(path)
    gt = simulate_section(sc, folder / "gt", progress=False)
    return load_context(sc, gt), gt


@pytest.mark.parametrize(("act", "better"), [(like_the_truth, "standing"), (always_brake, "all")])
def test_auto_keeps_the_floor_closer_to_the_truth_on_training_runs(
    slow_road: tuple[DeployContext, Path], tmp_path: Path, act, better: str
) -> None:
    """A policy that drives as the truth does is better off with "standing" (its 4.5 m/s
    left alone), one that always brakes with "all" (6 m/s, not a crawl); "auto" keeps
    each's better one, on a training run, and records both figures."""
    ctx, gt = slow_road
    drive, record = resolve_floor(ctx, Drive(act=act), tmp_path)
    assert drive.floor_on == better and record["chosen"] == better
    rmse = record["speed_rmse_mps"]
    other = "all" if better == "standing" else "standing"
    assert rmse[better] < 0.6 * rmse[other], rmse
    splits = split_runs(pd.read_csv(gt / "runs.csv")["run"].unique(), 0.25, ctx.sc.seed)
    assert record["training_runs"] == [int(splits["train"][0])]
    run = str(record["training_runs"][0])  # one run: its own figure is the pooled one
    assert {k: v[run] for k, v in record["speed_rmse_by_run_mps"].items()} == rmse
    assert not set(record["training_runs"]) & set(ctx.held_out)
    assert not (tmp_path.exists() and any(tmp_path.rglob("*.xml")))  # SUMO's files removed
    if better == "standing":  # the held-out run deployed as the fixed choice deploys it
        fixed = dataclasses.replace(ctx.sc.deploy, safety_floor_on="standing")
        ctx_fixed = dataclasses.replace(ctx, sc=dataclasses.replace(ctx.sc, deploy=fixed))
        a = run_method(ctx, drive, tmp_path / "auto").detectors
        b = run_method(ctx_fixed, Drive(act=act), tmp_path / "fixed").detectors
        pd.testing.assert_frame_equal(a, b)


def test_the_choice_never_reads_the_held_out_runs(
    slow_road: tuple[DeployContext, Path], tmp_path: Path
) -> None:
    """The truth's detectors of every run but the training runs the choice deploys on made
    nonsense (speeds x 5): the same figures and the same choice."""
    ctx, gt = slow_road
    before = choose_floor(ctx, Drive(act=like_the_truth), tmp_path / "a", 1)
    spoiled = tmp_path / "gt"
    shutil.copytree(gt, spoiled)
    det = pd.read_csv(spoiled / "detectors.csv")
    other = ~det["run"].isin(before.runs)
    det.loc[other, "speed_mps"] *= 5.0
    det.to_csv(spoiled / "detectors.csv", index=False)
    after = choose_floor(
        dataclasses.replace(ctx, truth_dir=spoiled), Drive(act=like_the_truth), tmp_path / "b", 1
    )
    assert after == dataclasses.replace(before, wall_s=after.wall_s)
    assert set(ctx.held_out) <= set(det.loc[other, "run"])


def test_a_floor_that_never_acts_is_a_tie_deployed_once(
    slow_road: tuple[DeployContext, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A policy that cruises at 8 m/s, above the floor of "all" (6 m/s), is never raised:
    "standing" would drive the same runs, so the choice deploys once, records a tie and
    keeps "all"."""
    calls: list[str | None] = []

    def counted(ctx: DeployContext, drive: Drive, *args, **kwargs):
        calls.append(drive.floor_on)
        return run_method(ctx, drive, *args, **kwargs)

    monkeypatch.setattr(floor_choice, "run_method", counted)
    ctx, _ = slow_road
    choice = choose_floor(ctx, Drive(act=lambda obs: (8.0 - obs[:, 0]) / 0.5), tmp_path, 1)
    assert calls == ["all"] and choice.deployed == ("all",)
    assert choice.chosen == "all"
    assert choice.speed_rmse_mps["all"] == choice.speed_rmse_mps["standing"] > 1.0
    (line,) = floor_choice_lines({"policy": choice.record()})
    assert "`standing` the same: `all` raised no command there" in line
    assert f"`all` {choice.speed_rmse_mps['all']:.3f} m/s" in line and "`standing` 1" not in line


def test_only_a_floored_speed_command_is_chosen_for(slow_road: tuple[DeployContext, Path]) -> None:
    """No choice for a method without speed commands, without the safety layer or without
    a floor, nor where the scenario fixes the floor; the learned method's manifest records
    the option until the stage resolves it."""
    ctx, _ = slow_road
    sc = ctx.sc
    assert needs_choice(sc, Drive(act=always_brake))
    assert not needs_choice(sc, Drive())  # the oracle
    assert not needs_choice(sc, Drive(act=always_brake, safety="none"))
    assert not needs_choice(sc, Drive(act=always_brake, floor_on="all"))
    for key, value in (("safety_floor_share", 0.0), ("safety_floor_on", "all")):
        dep = dataclasses.replace(sc.deploy, **{key: value})
        assert not needs_choice(dataclasses.replace(sc, deploy=dep), Drive(act=always_brake))
    drive, _ = method_drive("sumo_default", sc, {}, None)
    assert not needs_choice(sc, drive)


def _cruise_checkpoint(sc, folder: Path) -> Path:
    """A policy.pt whose mean action is ``like_the_truth``'s, cloned by regression on
    random observations (speeds 0-12 m/s) in a second."""
    rng = np.random.default_rng(0)
    obs = np.column_stack(
        [rng.uniform(0.0, 12.0, 4096), np.full(4096, 30.0), rng.uniform(7.0, 200.0, 4096)]
    )
    obs = np.column_stack([obs, rng.uniform(-5.0, 5.0, 4096)])
    a_min, a_max = sc.bounds.accel_mps2
    y = torch.as_tensor(np.clip(like_the_truth(obs), a_min, a_max), dtype=torch.float32)
    shift, scale = obs.mean(axis=0), np.where(obs.std(axis=0) > 1e-6, obs.std(axis=0), 1.0)
    torch.manual_seed(0)
    agent = Agent(32, observation=sc.policy.observation, shift_scale=(shift, scale))
    x = torch.as_tensor(obs, dtype=torch.float32)
    opt = torch.optim.Adam(agent.actor.parameters(), lr=3e-3)
    for _ in range(300):
        loss = ((agent.dist(x).mean - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    payload = {
        "format": CHECKPOINT_FORMAT,
        "signature": signature(sc),
        "prior": "none",
        "hidden_size": 32,
        "state_dict": agent.state_dict(),
    }
    folder.mkdir(parents=True)
    torch.save(payload, folder / "policy.pt")
    return folder


def test_the_stage_deploys_the_chosen_floor_and_the_report_says_so(
    slow_road: tuple[DeployContext, Path], tmp_path: Path
) -> None:
    """``macromicro deploy`` with "auto": the policy that cruises as the truth does gets
    "standing" (its held-out run then barely raised by the floor, where "all" raised most
    of its steps on the training run); the method's manifest, the stage's and report.md's
    Deployment section record the choice and both training-run figures."""
    ctx, gt = slow_road
    sc = ctx.sc
    pol = _cruise_checkpoint(sc, tmp_path / "policy")
    out = tmp_path / "run" / "deploy"
    m = deploy(sc, gt, pol, out, progress=False, methods=["policy", "policy_no_safety"])
    choice = m["safety_floor_choice"]
    assert list(choice) == ["policy"] and choice["policy"]["chosen"] == "standing"
    rmse = choice["policy"]["speed_rmse_mps"]
    assert rmse["standing"] < 0.6 * rmse["all"], rmse
    own = read_manifest(out / "policy" / "manifest.json")
    assert own["safety_floor_on"] == "standing" and own["safety_floor_choice"] == choice["policy"]
    assert read_manifest(out / "policy_no_safety" / "manifest.json")["safety_floor_on"] is None
    assert read_manifest(out / MANIFEST)["safety_floor_choice"] == choice
    summary = pd.read_csv(out / SUMMARY).set_index("method")
    assert summary.loc["policy", "floor_acted_share"] < 0.05, summary.loc["policy"].to_dict()
    text = "\n".join(deployment_section(tmp_path / "run"))
    assert "kept `standing`" in text and f"`all` {rmse['all']:.3f} m/s" in text
    assert "policy_no_safety`: `deploy.safety_floor_on" not in text


@pytest.mark.parametrize(
    ("key", "value", "accepted"),
    [
        ("safety_floor_runs", 0, "[1, 10000]"),
        ("safety_floor_runs", "two", "[1, 10000]"),
        ("safety_floor_on", "best", "auto"),
    ],
)
def test_a_bad_floor_option_is_a_one_line_error(
    tmp_path: Path, key: str, value: object, accepted: str
) -> None:
    path = write_scenario(tmp_path, {f"deploy.{key}": value})
    with pytest.raises(UserError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg, msg
    assert f"deploy.{key}" in msg and accepted in msg, msg

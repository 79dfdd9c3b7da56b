"""The safety layer as a named option: its floor is the scenario key
``deploy.safety_floor_share`` (typed, ranged, one-line errors), and the deploy stage
deploys the learned policy with and without the layer (``policy_no_safety``), so that the
summary and the report give both, a collision of the unprotected policy as a figure.
Real SUMO, real torch."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import write_scenario
from deploy_nets import sparse_merge

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.safety import FLOOR_SHARE, safety_cap
from macromicro_sumo.deploy.stage import MANIFEST, SUMMARY, deploy
from macromicro_sumo.errors import UserError
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.checkpoint import CHECKPOINT_FORMAT, signature
from macromicro_sumo.report.deploy import deployment_markdown
from macromicro_sumo.road.physics import safe_speed
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run, simulate_section


@pytest.mark.parametrize("value", [1.5, -0.1, "fifth"])
def test_a_floor_share_out_of_range_is_a_one_line_error(tmp_path: Path, value: object) -> None:
    path = write_scenario(tmp_path, {"deploy.safety_floor_share": value})
    with pytest.raises(UserError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg, msg
    assert "deploy.safety_floor_share" in msg and "[0, 1]" in msg, msg


def test_the_floor_share_is_the_scenarios(tmp_path: Path) -> None:
    assert load_scenario(write_scenario(tmp_path / "a")).deploy.safety_floor_share == FLOOR_SHARE
    path = write_scenario(tmp_path / "b", {"deploy.safety_floor_share": 0.5})
    assert load_scenario(path).deploy.safety_floor_share == 0.5


@pytest.mark.parametrize("share", [0.0, 0.2, 0.5])
def test_a_standing_command_on_a_free_road_is_raised_to_the_share(share: float) -> None:
    """A car at 20 m/s on a 30 m/s lane, nothing ahead, commanded to stop at once: raised
    to share x 30 m/s (no more than it can reach in a step: 20 + 2.6 x 0.5); 0: no floor.
    Behind a leader standing 1 m ahead the floor is the safe speed, whatever the share."""
    obs = np.array([[20.0, 30.0, NO_LEADER_GAP_M, 0.0], [5.0, 30.0, 8.5, 5.0]])
    gap = np.array([NO_LEADER_GAP_M, 1.0])
    decel = np.full(2, 4.5)
    out, lowered, raised = safety_cap(
        np.zeros(2), obs, gap, decel, decel, np.array([-1, -1]), 0.5, 2.6, share
    )
    assert out[0] == pytest.approx(min(share * 30.0, 21.3))
    safe = safe_speed(gap[1:], np.zeros(1), decel[1:], decel[1:], 0.5)[0]
    assert 0.0 < safe <= 2.0  # 1 m a step: 1 m in the next, none after
    assert out[1] == (safe if share > 0 else 0.0)
    assert raised == (2 if share > 0 else 0) and lowered == 0


# Two runs of 30 + 90 s.
SIMULATION = {"warmup_s": 30.0, "duration_s": 90.0, "n_runs": 2}


def test_a_higher_floor_keeps_a_braking_policy_faster(tmp_path: Path) -> None:
    """A policy that always brakes at a_min drives at the floor: half the limit with
    deploy.safety_floor_share = 0.5, where the default fifth holds the cars near 6 m/s."""
    sc = load_scenario(sparse_merge(tmp_path, SIMULATION, deploy={"safety_floor_share": 0.5}))
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B", "C"], False)
    a_min = sc.bounds.accel_mps2[0]
    drv = SectionSpeedDriver(sc, section, 0, lambda obs: np.full(len(obs), a_min), "sumo")
    sim = Simulation(
        SumoOptions(
            sc.resolve(sc.network.net_file),
            (),
            sc.simulation.step_length_s,
            sc.seed,
            route_files=tuple(sc.resolve(r) for r in sc.network.route_files),
            user_demand=True,
        )
    )
    try:
        df, stats = record_run(sim, sc, section, 0, drv)
    finally:
        sim.close()
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    speed = df.loc[~df["observed"], "speed_mps"]
    assert speed.mean() > 0.5 * 30.0 * 0.85, speed.describe()
    assert drv.stats.floor_acted > 0.5 * drv.stats.vehicle_steps_driven


def _full_throttle_checkpoint(sc, folder: Path) -> Path:
    """A policy.pt whose mean action is full throttle everywhere (clipped at a_max): it
    runs into whoever is ahead unless something stops it."""
    torch.manual_seed(0)
    agent = Agent(16, observation=sc.policy.observation)
    with torch.no_grad():
        agent.actor[-1].weight.zero_()
        agent.actor[-1].bias.fill_(10.0)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "signature": signature(sc),
        "prior": "none",
        "hidden_size": 16,
        "state_dict": agent.state_dict(),
    }
    folder.mkdir(parents=True)
    torch.save(payload, folder / "policy.pt")
    return folder


def test_the_stage_deploys_the_policy_with_and_without_the_safety_layer(tmp_path: Path) -> None:
    """``policy_no_safety`` (in deploy.methods by default) is the same checkpoint with its
    commands applied exactly: at full throttle it collides, and that is a figure of the
    summary and of the report's table, beside the protected policy's 0; the floor share
    the protected one used (deploy.safety_floor_share) is what its row and line say."""
    sc = load_scenario(
        sparse_merge(tmp_path, SIMULATION, deploy={"fcd_s": 30.0, "safety_floor_share": 0.35})
    )
    assert "policy_no_safety" in sc.deploy.methods  # on by default
    gt = simulate_section(sc, tmp_path / "gt", progress=False)
    pol = _full_throttle_checkpoint(sc, tmp_path / "policy")
    methods = ["policy", "policy_no_safety"]
    m = deploy(sc, gt, pol, tmp_path / "dep", progress=False, methods=methods)
    assert m["methods"] == methods
    summary = pd.read_csv(tmp_path / "dep" / SUMMARY).set_index("method")
    safe, bare = summary.loc["policy"], summary.loc["policy_no_safety"]
    assert safe["collisions"] == 0 and safe["teleports"] == 0, safe.to_dict()
    assert bare["collisions"] > 0, bare.to_dict()  # measured, not raised
    assert safe["safety"] == "sumo" and safe["safety_floor_share"] == 0.35
    assert bare["safety"] == "none" and np.isnan(bare["safety_floor_share"])
    assert safe["safety_acted"] > 0 and bare["safety_acted"] == bare["floor_acted"] == 0
    assert bare["vehicle_steps_driven"] > 0 and safe["vehicle_steps_driven"] > 0
    assert m["totals"]["policy_no_safety"]["collisions"] == bare["collisions"]
    text = deployment_markdown(summary.reset_index())
    assert "| policy_no_safety " in text and "| policy " in text
    assert f"`policy_no_safety`: {bare['collisions']:.0f} collisions" in text
    assert "(35% of the lane's limit)" in text
    # The unprotected run's own manifest says so.
    manifest = pd.read_json(tmp_path / "dep" / "policy_no_safety" / "manifest.json", typ="series")
    assert manifest["safety"] == "none"
    assert (tmp_path / "dep" / MANIFEST).is_file()

"""``policy.observation = "lookahead_length"``: the own vehicle length after the look-ahead.

On a merge whose demand mixes 5 m cars and 12 m trucks: the section env, the demand env,
the micro pairs and the deployment give each vehicle its own vType's length, and the scene
features are the look-ahead's, unchanged; the generated vehicles are drawn from the
demand's vTypes; PPO trains on it and the policy loads.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import CAR, merge_scenario  # noqa: E402

from macromicro_sumo.data.section import section_snapshots  # noqa: E402
from macromicro_sumo.deploy.drivers import SectionSpeedDriver  # noqa: E402
from macromicro_sumo.deploy.drivers import section_observations as deploy_observations  # noqa: E402
from macromicro_sumo.env.demand import DemandCore  # noqa: E402
from macromicro_sumo.env.section import SectionCore  # noqa: E402
from macromicro_sumo.env.section_bank import build_section_bank  # noqa: E402
from macromicro_sumo.env.section_envs import true_section_completion  # noqa: E402
from macromicro_sumo.errors import UserError  # noqa: E402
from macromicro_sumo.evaluation.micro_data import micro_pairs  # noqa: E402
from macromicro_sumo.policy.checkpoint import load_policy  # noqa: E402
from macromicro_sumo.policy.ppo import train_policy  # noqa: E402
from macromicro_sumo.road.physics import (  # noqa: E402
    OBSERVATION_FEATURES,
    idm_accel,
    set_own_features,
)
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402

TRUCK = (
    '<vType id="truck" vClass="truck" length="12" minGap="2.5" accel="1.0" decel="4.0" '
    'sigma="0.5" speedFactor="0.8" speedDev="0.05"/>'
)
LENGTH_OF = {"car": 5.0, "truck": 12.0}
COL = OBSERVATION_FEATURES["lookahead_length"].index("length_m")


def act(obs: np.ndarray) -> np.ndarray:
    """IDM on the observation, the leader taken 5 m long."""
    return idm_accel(obs[:, 0], obs[:, 2] - 5.0, obs[:, 3], 30.0, 1.2, 2.0, 3.0, 2.5)


@pytest.fixture(scope="module")
def mixed(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth) of the merge with a truck in every third main-road vehicle:
    2 runs of 60 s warm-up + 120 s, 40% instrumented."""
    folder = tmp_path_factory.mktemp("own_length")
    path = merge_scenario(
        folder,
        {"warmup_s": 60.0, "duration_s": 120.0, "n_runs": 2},
        policy={"observation": "lookahead_length", "demand_horizon_s": 30.0},
    )
    text = path.read_text().replace("penetration = 0.2", "penetration = 0.4")
    path.write_text(text)
    (folder / "net" / "merge.rou.xml").write_text(
        f"<routes>\n    {CAR}\n    {TRUCK}\n"
        '    <route id="main" edges="A B C"/>\n    <route id="ramp" edges="R B C"/>\n'
        '    <flow id="m" type="car" route="main" begin="0" end="3600" vehsPerHour="1200" '
        'departLane="best" departSpeed="max"/>\n'
        '    <flow id="t" type="truck" route="main" begin="0" end="3600" vehsPerHour="600" '
        'departLane="best" departSpeed="max"/>\n'
        '    <flow id="r" type="car" route="ramp" begin="0" end="3600" vehsPerHour="400" '
        'departLane="best" departSpeed="max"/>\n</routes>\n'
    )
    sc = load_scenario(path)
    gt = simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(gt, sc)


def with_observation(sc, observation: str):
    return dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, observation=observation))


def test_scene_only_observations_are_left_as_they_are() -> None:
    obs = np.arange(12.0).reshape(2, 6)
    assert set_own_features(obs, "lookahead", None) is obs
    np.testing.assert_array_equal(obs, np.arange(12.0).reshape(2, 6))
    with pytest.raises(ValueError, match="length"):
        set_own_features(np.zeros((2, 7)), "lookahead_length", None)


def test_micro_pairs_carry_each_observed_vehicles_length(mixed) -> None:
    sc, truth = mixed
    obs, acc = micro_pairs(sc, truth, truth.runs)
    scene, acc0 = micro_pairs(with_observation(sc, "lookahead"), truth, truth.runs)
    assert obs.shape == (len(scene), 7)
    np.testing.assert_array_equal(obs[:, :6], scene)
    np.testing.assert_array_equal(acc, acc0)
    # Every pair is a car's or a truck's, both kinds are there, in about the demand's mix.
    assert set(np.unique(obs[:, COL])) == {5.0, 12.0}
    truck_share = float(np.mean(obs[:, COL] == 12.0))
    assert 0.1 < truck_share < 0.5, truck_share
    # Trucks (accel 1.0) never out-accelerate their vType; cars (2.6) do at times.
    assert acc[obs[:, COL] == 12.0].max() <= 1.0 + 1e-6
    assert acc[obs[:, COL] == 5.0].max() > 1.0


def test_a_vtype_without_a_length_is_refused(mixed) -> None:
    sc, truth = mixed
    vt = truth.vtypes[truth.vtypes["vtype"] != "truck"]
    broken = dataclasses.replace(truth, vtypes=vt)
    with pytest.raises(UserError, match=r"vtypes.csv: length_m of vType truck"):
        micro_pairs(sc, broken, truth.runs)


def test_section_env_observes_each_slots_length_and_ppo_trains(mixed, tmp_path: Path) -> None:
    sc, truth = mixed
    snaps = section_snapshots(truth, sc, truth.runs)

    bank = build_section_bank(sc, truth, snaps, true_section_completion, 4, 0)
    # Generated vehicles: every vType by the demand's shares, seeded; the typical one
    # (the car) alone where the policy does not observe its length.
    gen = bank.length_m[bank.hidden]
    share = dict(zip(truth.vtypes["vtype"], truth.vtypes["vehicles"], strict=True))
    assert set(np.unique(gen)) == {5.0, 12.0}
    assert abs(np.mean(gen == 12.0) - share["truck"] / sum(share.values())) < 0.05
    again = build_section_bank(sc, truth, snaps, true_section_completion, 4, 0)
    np.testing.assert_array_equal(again.length_m, bank.length_m)
    assert (again.accel_mps2[bank.hidden & (bank.length_m == 12.0)] == 1.0).all()
    scene_only = build_section_bank(
        with_observation(sc, "lookahead"), truth, snaps, true_section_completion, 4, 0
    )
    assert (scene_only.length_m[scene_only.hidden] == 5.0).all()
    net = Path(sc.network.net_file)
    core = SectionCore(sc, truth.section, bank, net, seed=0)
    trucks = 0
    try:
        for ep in range(0, len(bank), 2):
            obs = core.reset(ep)
            on = core.active
            assert obs.shape[1] == 7
            np.testing.assert_array_equal(obs[on, COL], bank.length_m[ep, on])
            assert (obs[~on] == 0.0).all()
            trucks += int(np.sum(obs[on & bank.observed[ep], COL] == 12.0))
            res = core.step(act(obs[bank.hidden[ep]]))
            np.testing.assert_array_equal(res.obs[res.active, COL], bank.length_m[ep, res.active])
    finally:
        core.close()
    assert trucks > 0  # observed trucks are in the episodes with their own length
    torch.set_num_threads(1)
    sc = dataclasses.replace(
        sc, policy=dataclasses.replace(sc.policy, episodes_per_update=4, horizon=4)
    )
    res = train_policy(
        sc,
        bank,
        tmp_path,
        updates=1,
        progress=False,
        make_core=lambda b, seed: SectionCore(sc, truth.section, b, net, seed=seed),
    )
    agent = load_policy(tmp_path / "policy.pt", sc)
    assert agent.shift.shape == (7,) and torch.equal(agent.shift, res["agent"].shift)
    # The length's normalisation is the bank's: cars and trucks, so a spread above 0.
    assert 5.0 < float(agent.shift[COL]) < 12.0 and float(agent.scale[COL]) > 0.5


def test_demand_env_and_deployment_observe_the_same_lengths(mixed) -> None:
    """One SUMO state: the demand core's observation and the deployment driver's agree in
    every column, the last one each vehicle's vType's length."""
    sc, truth = mixed
    core = DemandCore(sc, truth, truth.runs, 40)
    seen: set[float] = set()
    try:
        core.reset(int(truth.runs[0]), 90.0)
        for t in range(24):
            vids, obs = core.observe()
            if t % 8 == 7 and vids:
                assert obs.shape == (len(vids), 7)
                want = np.array([LENGTH_OF[core.types[v]] for v in vids])
                np.testing.assert_array_equal(obs[:, COL], want)
                seen.update(want.tolist())
                drv = SectionSpeedDriver(sc, truth.section, int(truth.runs[0]), act, "none")
                drv.types = dict(core.types)
                drv.vtypes = dict(core.vtypes)
                drv.shape_of = {v: core.vtypes[k].shape for v, k in core.types.items()}
                drv.has_lights = False
                dep, _, _ = deploy_observations(drv, core.sim, vids, core.lane_states())
                np.testing.assert_allclose(obs, dep, atol=1e-9)
            core.step(act(obs))
    finally:
        core.close()
    assert seen == {5.0, 12.0}

"""``deploy.command_brake``: a driven vehicle's command brakes at most at the decel the
safety layer plans its stop with ("decel", the default), not at the scenario's lower
bound ("bounds"), unless what is ahead asks for more (then the layer's braking stands). In
numpy and in real SUMO: IDM cars (decel 3.0) under a policy that always brakes at the
bound (-4.5 m/s^2) make SUMO's emergency brakings with "bounds", none with "decel"."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import netconvert
from section_files import section_scenario
from test_safety import _run_section

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.safety import command_brake, speed_commands
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.deploy_settings import DeployConfig
from macromicro_sumo.scenario.load import load_scenario

# SUMO's IDM with the drawn networks' car decel: comfortable braking 3.0 m/s^2, below the
# examples' bound of -4.5.
IDM_CAR = (
    '<vType id="idm" carFollowModel="IDM" length="5" minGap="2.5" accel="2.0" decel="3.0" '
    'emergencyDecel="9" tau="1.2" speedFactor="1.0" speedDev="0"/>'
)


def _road(folder: Path, brake: str) -> Path:
    """One lane A (600 m) -> B (600 m), limit 30 m/s, IDM cars entering at 25 m/s every 4 s
    (100 m apart): nothing ahead of any car asks for braking. 60 s, no warm-up."""
    folder.mkdir(parents=True, exist_ok=True)
    nodes = "\n".join(
        [
            '<node id="n0" x="0" y="0"/>',
            '<node id="n1" x="600" y="0"/>',
            '<node id="n2" x="1200" y="0"/>',
        ]
    )
    edges = "\n".join(
        [
            '<edge id="A" from="n0" to="n1" numLanes="1" speed="30"/>',
            '<edge id="B" from="n1" to="n2" numLanes="1" speed="30"/>',
        ]
    )
    net = netconvert(folder, nodes, edges)
    routes = folder / "road.rou.xml"
    routes.write_text(
        f"<routes>\n    {IDM_CAR}\n"
        '    <flow id="f" type="idm" begin="0" end="3600" period="4" departSpeed="25">'
        '<route edges="A B"/></flow>\n</routes>\n'
    )
    deploy = {} if brake == "decel" else {"command_brake": brake}  # decel: the default
    return section_scenario(
        folder / "road.toml",
        net,
        routes,
        ["A", "B"],
        seed=3,
        penetration=0.05,
        simulation={"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 2},
        detectors={"interval_s": 30.0, "auto_spacing_m": 300.0},
        policy={"observation": "lookahead"},
        deploy=deploy,
    )


@pytest.mark.parametrize("brake", ["bounds", "decel"])
def test_a_policy_braking_at_the_bound_brakes_idm_cars_at_their_decel(
    tmp_path: Path, brake: str
) -> None:
    """Every driven car is commanded a_min = -4.5 m/s^2 on a free road. "bounds" applies it:
    each braking step is an emergency braking by SUMO's count (decel 3.0); "decel" brakes
    each at its 3.0: none, and every car still slows to the floor (a fifth of 30 m/s)."""
    sc = load_scenario(_road(tmp_path, brake))
    assert sc.bounds.accel_mps2[0] < -3.0
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B"], False)
    a_min = sc.bounds.accel_mps2[0]
    drv = SectionSpeedDriver(sc, section, 0, lambda obs: np.full(len(obs), a_min), "sumo")
    df, stats = _run_section(sc, drv)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    driven = df[~df["observed"]].sort_values(["vehicle_id", "time_s"])
    assert driven["vehicle_id"].nunique() >= 3
    dv = driven.groupby("vehicle_id")["speed_mps"].diff().dropna()
    hardest = -dv.min() / sc.simulation.step_length_s
    if brake == "bounds":
        assert drv.stats.emergency_brakings > 20, drv.stats
        assert hardest == pytest.approx(4.5, abs=0.05)
    else:
        assert drv.stats.emergency_brakings == 0, drv.stats
        assert hardest == pytest.approx(3.0, abs=0.05)
    # Braked down to the floor either way: the command's bound, not the policy, changed.
    assert driven["speed_mps"].median() == pytest.approx(0.2 * 30.0, abs=0.1)


def test_the_layer_still_brakes_harder_where_what_is_ahead_asks() -> None:
    """A car at 20 m/s 8 m behind a standing obstacle: its safe speed is far below
    20 - 3.0 x 0.5; "decel" bounds the policy's braking, not the layer's: the command is
    the safe speed, a real emergency. A free car beside it brakes at its decel."""
    v = np.array([20.0, 20.0])
    gap = np.array([8.0, NO_LEADER_GAP_M])
    obs = np.column_stack([v, np.full(2, 30.0), gap, v, np.full(2, 30.0), np.full(2, 500.0)])
    decel, lead_decel = np.full(2, 3.0), np.full(2, 9.0)

    def layer() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return gap, decel, lead_decel, np.full(2, -1)

    class Sc:  # the tables speed_commands reads, the examples' values
        class bounds:
            accel_mps2 = (-4.5, 2.6)

        class simulation:
            step_length_s = 0.5

        # The package's deploy defaults (command_brake decel, floor 0.2), the floor on all:
        # a setting the layer reads later is there with its default.
        deploy = DeployConfig(safety_floor_on="all")

    cmd = speed_commands(Sc, lambda o: np.full(len(o), -4.5), "sumo", DriveStats(), obs, layer)
    assert cmd[0] < 20.0 - 4.5 * 0.5  # the layer's braking, beyond the bound even
    assert cmd[1] == pytest.approx(20.0 - 3.0 * 0.5)
    np.testing.assert_array_equal(command_brake(-4.5, decel, "bounds"), -4.5)
    np.testing.assert_array_equal(command_brake(-4.5, np.array([3.0, 9.0]), "decel"), [-3.0, -4.5])

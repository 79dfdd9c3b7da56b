"""Tiny SUMO networks for the deployment tests, built by netconvert from plain XML, and a
small policy cloned from IDM (the deployment needs one that drives sensibly, quickly)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
from conftest import light_road, netconvert, small_section_scenario
from section_files import section_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.road.physics import OBSERVATION_FEATURES, idm_accel
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

D = TypeVar("D", bound=SectionSpeedDriver)

CAR = (
    '<vType id="car" length="5" minGap="2.5" accel="2.6" decel="4.5" sigma="0.5" '
    'speedFactor="1.0" speedDev="0.1"/>'
)


def merge_net(folder: Path, main_vph: float = 1800.0, ramp_vph: float = 500.0) -> tuple[Path, Path]:
    """Mainline A (2 lanes) -> B (3 lanes: the on-ramp R adds an acceleration lane on the
    right, so A's lanes 0 and 1 go on as B's 1 and 2) -> C (2 lanes: B's lane 0 ends, its
    vehicles must change lanes). Returns (net, routes)."""
    folder.mkdir(parents=True, exist_ok=True)
    nodes = "\n".join(
        [
            '<node id="n0" x="0" y="0"/>',
            '<node id="n1" x="500" y="0"/>',
            '<node id="n2" x="800" y="0"/>',
            '<node id="n3" x="1300" y="0"/>',
            '<node id="r0" x="300" y="-40"/>',
        ]
    )
    edges = "\n".join(
        [
            '<edge id="A" from="n0" to="n1" numLanes="2" speed="30"/>',
            '<edge id="R" from="r0" to="n1" numLanes="1" speed="25"/>',
            '<edge id="B" from="n1" to="n2" numLanes="3" speed="30"/>',
            '<edge id="C" from="n2" to="n3" numLanes="2" speed="30"/>',
        ]
    )
    cons = "\n".join(
        [
            '<connection from="A" to="B" fromLane="0" toLane="1"/>',
            '<connection from="A" to="B" fromLane="1" toLane="2"/>',
            '<connection from="R" to="B" fromLane="0" toLane="0"/>',
            '<connection from="B" to="C" fromLane="1" toLane="0"/>',
            '<connection from="B" to="C" fromLane="2" toLane="1"/>',
        ]
    )
    net = netconvert(folder, nodes, edges, cons)
    routes = folder / "merge.rou.xml"
    routes.write_text(
        f"<routes>\n    {CAR}\n"
        '    <route id="main" edges="A B C"/>\n    <route id="ramp" edges="R B C"/>\n'
        f'    <flow id="m" type="car" route="main" begin="0" end="3600" vehsPerHour="{main_vph}" '
        'departLane="best" departSpeed="max"/>\n'
        f'    <flow id="r" type="car" route="ramp" begin="0" end="3600" vehsPerHour="{ramp_vph}" '
        'departLane="best" departSpeed="max"/>\n</routes>\n'
    )
    return net, routes


def merge_scenario(
    folder: Path,
    simulation: dict,
    *,
    auto_spacing_m: float = 200.0,
    main_vph: float = 1800.0,
    ramp_vph: float = 500.0,
    seed: int = 9,
    penetration: float = 0.2,
    **tables: dict,
) -> Path:
    """``folder/merge.toml``: the merge (``merge_net``) as a section A -> B -> C with the
    user's route files, ``penetration`` instrumented, loops every ``auto_spacing_m``, the
    given ``[simulation]`` and further tables (``policy``, ``deploy``, ...)."""
    net, routes = merge_net(folder / "net", main_vph, ramp_vph)
    return section_scenario(
        folder / "merge.toml",
        net,
        routes,
        ["A", "B", "C"],
        seed=seed,
        penetration=penetration,
        simulation=simulation,
        detectors={"interval_s": 30.0, "auto_spacing_m": auto_spacing_m},
        **tables,
    )


def sparse_merge(folder: Path, simulation: dict | None = None, **tables: dict) -> Path:
    """The safety layer's merge: ``merge_scenario`` with 5% instrumented (nearly every car
    driven), the look-ahead observation, by default 2 runs of 120 s without warm-up."""
    simulation = simulation or {"warmup_s": 0.0, "duration_s": 120.0, "n_runs": 2}
    tables = {"policy": {"observation": "lookahead"}} | tables
    return merge_scenario(
        folder, simulation, auto_spacing_m=300.0, seed=5, penetration=0.05, **tables
    )


def light_net(folder: Path) -> tuple[Path, Path, Path]:
    """One lane A (400 m) -> a traffic light that stays red -> B (200 m); one car.
    Returns (net, routes, additional with the all-red program)."""
    net = light_road(folder, 400.0, 200.0, 20.0)
    routes = folder / "light.rou.xml"
    routes.write_text(
        f"<routes>\n    {CAR}\n"
        '    <vehicle id="v0" type="car" depart="0" departSpeed="15"><route edges="A B"/></vehicle>\n'
        '    <vehicle id="probe" type="car" depart="1"><route edges="A B"/></vehicle>\n'
        "</routes>\n"
    )
    red = folder / "red.add.xml"
    red.write_text(
        '<additional>\n    <tlLogic id="tl" type="static" programID="red" offset="0">\n'
        '        <phase duration="10000" state="r"/>\n    </tlLogic>\n</additional>\n'
    )
    return net, routes, red


def lane_drop_net(
    folder: Path, a_m: float = 600.0, b_m: float = 400.0, speed_mps: float = 25.0
) -> Path:
    """A (2 lanes, ``a_m``) -> B (1 lane, ``b_m``), both at ``speed_mps``: A's lane 1 goes on
    as B's lane 0, A's lane 0 ends (a lane drop)."""
    return netconvert(
        folder,
        f'<node id="n0" x="0" y="0"/>\n<node id="n1" x="{a_m:g}" y="0"/>\n'
        f'<node id="n2" x="{a_m + b_m:g}" y="0"/>',
        f'<edge id="A" from="n0" to="n1" numLanes="2" speed="{speed_mps:g}"/>\n'
        f'<edge id="B" from="n1" to="n2" numLanes="1" speed="{speed_mps:g}"/>',
        '<connection from="A" to="B" fromLane="1" toLane="0"/>',
    )


def lane_drop_traffic(
    folder: Path,
    vtype: str,
    platoon_m: Sequence[float],
    mergers_m: Sequence[float],
    speed_mps: float,
    merger_id: str = "m",
) -> Path:
    """The routes of ``lane_drop_net`` (A B): cars of ``vtype`` (its XML, id "car") leaving at
    0 s at ``speed_mps``, a platoon ``p00``, ``p01``, ... on A's lane 1 at ``platoon_m`` and
    mergers ``{merger_id}0``, ... on the ending lane 0 at ``mergers_m``."""

    def cars(prefix: str, lane: int, at: Sequence[float], width: int) -> str:
        return "\n".join(
            f'    <vehicle id="{prefix}{k:0{width}d}" type="car" route="r" depart="0" '
            f'departLane="{lane}" departPos="{x:g}" departSpeed="{speed_mps:g}"/>'
            for k, x in enumerate(at)
        )

    platoon, merging = cars("p", 1, platoon_m, 2), cars(merger_id, 0, mergers_m, 1)
    routes = folder / "lane_drop.rou.xml"
    routes.write_text(
        f'<routes>\n    {vtype}\n    <route id="r" edges="A B"/>\n{platoon}\n{merging}\n</routes>\n'
    )
    return routes


def recorded_drive(
    folder: Path,
    net: Path,
    routes: Path,
    driver: type[D],
    duration_s: float,
    limit_mps: float,
    **deploy: str,
) -> tuple[SectionScenario, D, Simulation]:
    """Every car of ``routes`` on ``net``'s section A B commanded by ``driver`` (a
    ``SectionSpeedDriver`` that records what it does, ``rows`` emptied) with a policy cloned
    from IDM at ``limit_mps``, ``deploy.merge = "sumo"`` and the ``deploy`` settings given;
    its SUMO started (``duration_s`` of demand): the caller steps and closes it."""
    base = small_section_scenario(
        folder, net, routes, ["A", "B"], instrumented={"ids": []},
        simulation={"warmup_s": 0.0, "duration_s": duration_s, "n_runs": 2},
    )  # fmt: skip
    sc = dataclasses.replace(base, deploy=dataclasses.replace(base.deploy, merge="sumo", **deploy))
    agent = policy_batch(idm_agent("lookahead", limit_mps))
    drv = driver(sc, read_section(net, ["A", "B"], False), 0, agent, "sumo")
    drv.rows = []
    opts = SumoOptions(net, (), sc.simulation.step_length_s, sc.seed, route_files=(routes,))
    return sc, drv, Simulation(dataclasses.replace(opts, user_demand=True))


def idm_agent(observation: str, limit: float, seed: int = 0, steps: int = 400) -> Agent:
    """An agent whose mean action is IDM's (v0 = limit, T 1.2 s, a 2, b 3, s0 2 m, 5 m cars),
    cloned by regression on random observations: a sensible small policy in seconds."""
    rng = np.random.default_rng(seed)
    n = 8192
    v = rng.uniform(0.0, limit * 1.1, n)
    spacing = np.exp(rng.uniform(np.log(5.5), np.log(250.0), n))
    dv = rng.uniform(-8.0, 12.0, n)
    dv = np.minimum(dv, v)  # the leader's speed is never negative
    cols = [v, np.full(n, limit), spacing, dv]
    if len(OBSERVATION_FEATURES[observation]) > 4:
        cols += [np.full(n, limit), rng.uniform(0.0, 500.0, n)]
    obs = np.stack(cols, axis=1)
    a = idm_accel(v, spacing - 5.0, dv, limit, 1.2, 2.0, 3.0, 2.0)
    a = np.clip(a, -9.0, 2.6)
    shift, scale = obs.mean(axis=0), np.where(obs.std(axis=0) > 1e-6, obs.std(axis=0), 1.0)
    torch.manual_seed(seed)
    agent = Agent(64, observation=observation, shift_scale=(shift, scale))
    x = torch.as_tensor(obs, dtype=torch.float32)
    y = torch.as_tensor(a, dtype=torch.float32)
    opt = torch.optim.Adam(agent.actor.parameters(), lr=3e-3)
    for _ in range(steps):
        idx = torch.as_tensor(rng.integers(0, n, 1024))
        loss = ((agent.dist(x[idx]).mean - y[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    agent.eval()
    return agent


def twelve_cars() -> str:
    """A route file's text: 12 cars (``CAR``) leaving 2 s apart at their top speed on route
    A B (a queue's worth for the one-lane roads of ``queue_at_light`` and the jam tests)."""
    cars = "\n".join(
        f'<vehicle id="c{k:02d}" type="car" depart="{2 * k}" departSpeed="max">'
        '<route edges="A B"/></vehicle>'
        for k in range(12)
    )
    return f"<routes>\n{CAR}\n{cars}\n</routes>\n"


def queue_at_light(
    toml: Path, green_s: float, deploy: dict, b_m: float = 200.0, after_s: float = 40.0
) -> Path:
    """One lane A (150 m, 14 m/s) -> a light, red for the first ``green_s``, then green ->
    B (``b_m``); 12 cars leave 2 s apart and queue at the red; the run ends ``after_s``
    after the green. Returns the scenario file ``toml`` (its folder's ``net`` holds the
    files), deploying with ``deploy``."""
    folder = toml.parent / "net"
    net = light_road(folder, 150.0, b_m, 14.0)
    routes = folder / "queue.rou.xml"
    routes.write_text(twelve_cars())
    light = folder / "light.add.xml"
    light.write_text(
        '<additional>\n<tlLogic id="tl" type="static" programID="p" offset="0">\n'
        f'<phase duration="{green_s:g}" state="r"/>\n<phase duration="1000" state="G"/>\n'
        "</tlLogic>\n</additional>\n"
    )
    return section_scenario(
        toml,
        net,
        routes,
        ["A", "B"],
        seed=3,
        penetration=0.01,
        simulation={"warmup_s": 0.0, "duration_s": green_s + after_s, "n_runs": 1},
        detectors={"interval_s": 30.0},
        deploy=deploy,
    )

"""A standing leader where the vehicle's own vType stops: its minGap and jmStoplineGap.

SUMO's driver stops jmStoplineGap before a red line (its vType's; SUMO's default 1 m for
every carFollowModel) and stands minGap behind a vehicle. The observation's standing
leader (``road.leaders.standing_spacing_m``) is a standing vehicle minGap beyond that
stop, so that a reader's gap (spacing - length - own minGap) is 0 where SUMO's driver
stands. Before (stop 34), every vehicle took 1 m and 2.5 m: a vType with minGap 4 m and
jmStoplineGap 3 m read 0.5 m of room where SUMO's driver of that type had none.

Real SUMO: one lane A (300 m) into a light that stays red, a queue of "far" cars (minGap
4 m, jmStoplineGap 3 m) and default cars.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import netconvert, one_phase_program, prior_alone, small_section_scenario
from section_files import routes_file, section_scenario, vtype

from macromicro_sumo.data.section import section_snapshots, stop_lines_at
from macromicro_sumo.deploy.observe import STANDING, LaneTable, Table, observe_rows
from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.env.section_bank import build_section_bank, standing_gaps
from macromicro_sumo.env.section_envs import true_section_completion
from macromicro_sumo.env.section_observations import section_observations
from macromicro_sumo.road.leaders import stop_distance_m
from macromicro_sumo.road.section import STOP, read_section
from macromicro_sumo.road.vtype import read_vtype
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import load_section_truth, simulate_section

FAR = {"length": 5, "minGap": 4, "jmStoplineGap": 3, "sigma": 0, "speedDev": 0}
CAR = {"length": 5, "sigma": 0, "speedDev": 0}  # SUMO's defaults: minGap 2.5, stop gap 1


def light_net(folder: Path) -> tuple[Path, Path]:
    """A (1 lane, 300 m) -> a traffic light that stays red -> B (200 m); (net, red program)."""
    nodes = "\n".join(
        [
            '<node id="n0" x="0" y="0"/>',
            '<node id="tl" x="300" y="0" type="traffic_light"/>',
            '<node id="n2" x="500" y="0"/>',
        ]
    )
    edges = "\n".join(
        [
            '<edge id="A" from="n0" to="tl" numLanes="1" speed="15"/>',
            '<edge id="B" from="tl" to="n2" numLanes="1" speed="15"/>',
        ]
    )
    net = netconvert(folder, nodes, edges)
    return net, one_phase_program(folder, "tl", "r")


@pytest.fixture(scope="module")
def queue(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth, net, red program): far cars and default cars alternating
    every 4 s from t = 0 into the red light, 20 s warm-up and 40 s recorded."""
    folder = tmp_path_factory.mktemp("vtype_stop_gaps")
    net, red = light_net(folder)
    routes = routes_file(
        folder / "queue.rou.xml",
        [vtype("far", **FAR), vtype("car", **CAR)],
        ['<flow id="f" type="far" begin="0" end="60" period="8" departSpeed="10">'
         '<route edges="A B"/></flow>',
         '<flow id="c" type="car" begin="4" end="60" period="8" departSpeed="10">'
         '<route edges="A B"/></flow>'],
    )  # fmt: skip
    path = section_scenario(
        folder / "queue.toml",
        net,
        routes,
        ["A", "B"],
        seed=1,
        penetration=1.0,
        simulation={"warmup_s": 20.0, "duration_s": 40.0, "n_runs": 1},
        detectors={"interval_s": 20.0},
        generator={"snapshot_every_s": 5.0},
        network={
            "kind": "sumo",
            "net_file": str(net),
            "route_files": [str(routes)],
            "additional_files": [str(red)],
        },
    )
    sc = load_scenario(path)
    truth = load_section_truth(simulate_section(sc, folder / "gt", progress=False), sc)
    return sc, truth, net, red


def test_vtypes_csv_records_each_vtypes_gaps_and_the_envs_take_them(queue) -> None:
    """vtypes.csv: far 4 m / 3 m, car SUMO's 2.5 m / 1 m; ``standing_gaps`` reads them, and
    the bank carries them per slot. Without the columns, and for field data, the defaults."""
    sc, truth, _, _ = queue
    vt = truth.vtypes.set_index("vtype")
    assert vt.loc["far", ["min_gap_m", "stopline_gap_m"]].tolist() == [4.0, 3.0]
    assert vt.loc["car", ["min_gap_m", "stopline_gap_m"]].tolist() == [2.5, 1.0]
    gaps = standing_gaps(sc, truth)
    assert gaps["min_gap_m"] == ({"far": 4.0, "car": 2.5}, 2.5)
    assert gaps["stopline_gap_m"] == ({"far": 3.0, "car": 1.0}, 1.0)
    older = dataclasses.replace(truth, vtypes=truth.vtypes.drop(columns=["stopline_gap_m"]))
    assert standing_gaps(sc, older)["stopline_gap_m"] == ({}, 1.0)
    files = dataclasses.replace(sc, data=dataclasses.replace(sc.data, source="files"))
    assert all(known == {} for known, _ in standing_gaps(files, truth).values())
    snaps = section_snapshots(truth, sc, np.array([0]))
    bank = build_section_bank(sc, truth, snaps, true_section_completion, 4, 0)
    pairs = set(zip(bank.min_gap_m[bank.valid], bank.stopline_gap_m[bank.valid], strict=True))
    assert pairs == {(4.0, 3.0), (2.5, 1.0)}
    plain = build_section_bank(sc, older, snaps, true_section_completion, 4, 0)
    assert plain.stopline_gap_m is None and plain.gaps_of(0)["stopline_gap_m"] is None


def test_the_envs_queue_stands_where_sumos_drivers_stand(queue) -> None:
    """Every standing vehicle of the recorded queue (the micro pairs' and envs' observation
    of it, ``section_observations`` with each vType's gaps): a reader's gap spacing -
    length - own minGap is 0 (+- 0.05 m), the head a far car 3 m before the line. Before:
    0.5 m for a far car at the head (1 m and 2.5 m)."""
    sc, truth, _, _ = queue
    traj = truth.trajectories
    last = traj[traj["time_s"] == traj["time_s"].max()]
    gaps = standing_gaps(sc, truth)
    stops = stop_lines_at(truth, 0, np.array([last["time_s"].iloc[0]]))
    own = {k: last["vtype"].map(of).to_numpy(dtype=float) for k, (of, _) in gaps.items()}
    obs, leader, spacing = section_observations(
        truth.section,
        last["lane_index"].to_numpy(),
        last["arc_m"].to_numpy(),
        last["speed_mps"].to_numpy(),
        np.ones(len(last), dtype=bool),
        "paper",
        *next(iter(stops.values())),
        length_m=np.full(len(last), 5.0),
        **own,
    )
    standing = last["speed_mps"].to_numpy() < 0.01
    assert standing.sum() >= 4
    head = np.flatnonzero(leader == STOP)
    assert len(head) == 1 and last["vtype"].iloc[head[0]] == "far"
    end_a = float(truth.section.lengths_m[0])
    assert last["arc_m"].iloc[head[0]] == pytest.approx(end_a - 3.0, abs=0.05)
    room = spacing - 5.0 - own["min_gap_m"]
    np.testing.assert_allclose(room[standing], 0.0, atol=0.05)


def test_the_deployment_stands_where_sumos_driver_stands(queue) -> None:
    """A far car driven by SUMO into the red light: the deployment's observation of it
    (``observe_rows`` with SUMO's minGap of its vType, ``stop_distance_m`` with its
    jmStoplineGap) leaves it no room where it stands, and on its approach puts the stop
    where SUMO then stops it (within 0.1 m). Before: 0.5 m of room."""
    _, _, net, red = queue
    folder = net.parent
    types = routes_file(folder / "types.rou.xml", [vtype("far", **FAR)])
    sim = Simulation(SumoOptions(net, (red,), 0.5, 1, route_files=(types,)))
    section = read_section(net, ["A", "B"], closed=False)
    seen = []
    try:
        sim.add_route("r", ["A", "B"])
        sim.add_vehicle("v", "r", "far", 0, 100.0, 10.0)
        for step in range(120):
            sim.step()
            if step in (2, 119):
                st = sim.vehicle_states()
                lanes, rows = ["A_0"], np.array([st.index["v"]])
                red_m = np.fmin(sim.stop_lines_m(["v"]), np.inf)
                lane_end = np.array([sim.lane_end_m("v", "A_0", 0.0)]) - st.pos_m[rows]
                stop = stop_distance_m(lane_end, red_m, FAR["jmStoplineGap"])
                shapes = Table.of_rows({"v": sim.vtype_shape("far")}, STANDING)
                obs = observe_rows(
                    LaneTable(section), "paper", ["v"], rows, lanes, st,
                    sim.leaders(["v"], 250.0), shapes, stop,
                )[0]  # fmt: skip
                seen.append(
                    (float(st.pos_m[rows[0]]), float(obs[0, 2]), float(st.speed_mps[rows[0]]))
                )
    finally:
        sim.close()
    (pos0, spacing0, _), (pos1, spacing1, speed1) = seen
    assert speed1 < 0.01 and pos1 == pytest.approx(300.0 - 3.0, abs=0.05)
    assert spacing1 - 5.0 - FAR["minGap"] == pytest.approx(0.0, abs=0.05)
    assert pos0 + spacing0 - 5.0 - FAR["minGap"] == pytest.approx(pos1, abs=0.1)


def test_the_deployment_reads_each_vtypes_stopline_gap_from_sumo(queue) -> None:
    """``read_vtype`` (the deployment's drivers' and the demand env's vType record) has the
    vType's jmStoplineGap as SUMO drives it: 3 m for far, SUMO's default 1 m for a vType
    that sets none (``Simulation.vtype_stopline_gap``: None). Before: 1 m for both."""
    _, _, net, red = queue
    types = routes_file(net.parent / "both.rou.xml", [vtype("far", **FAR), vtype("car", **CAR)])
    sim = Simulation(SumoOptions(net, (red,), 0.5, 1, route_files=(types,)))
    try:
        sim.step()
        far, car = read_vtype(sim, "far"), read_vtype(sim, "car")
        assert sim.vtype_stopline_gap("car") is None
    finally:
        sim.close()
    assert (far.stopline_gap_m, far.min_gap_m) == (3.0, 4.0)
    assert (car.stopline_gap_m, car.min_gap_m) == (1.0, 2.5)


def test_the_demand_env_stops_where_sumo_stops_a_vtype_with_its_own_stopline_gap(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """One far car (jmStoplineGap 3 m, minGap 4 m) from A into the light that stays red,
    driven by the demand env (``DemandCore``: SUMO's state, ``read_vtype``'s
    ``stopline_gap_m``, commands applied exactly) with the Krauss prior alone (the far
    type's minGap, residual 0): it stands where SUMO's own driver of that vType stands,
    3.0 m before the line (within 0.15 m; measured 3.000 m, SUMO's 3.001 m). With the
    vType's record at SUMO's default 1 m (as before 851dd00) it stands 1.000 m before it."""
    net, red = light_net(tmp_path)
    routes = routes_file(
        tmp_path / "one.rou.xml",
        [vtype("far", **FAR), vtype("car", **CAR)],
        ['<vehicle id="v0" type="far" depart="0" departSpeed="10" departPos="50">'
         '<route edges="A B"/></vehicle>',
         '<vehicle id="probe" type="car" depart="55"><route edges="A B"/></vehicle>'],
    )  # fmt: skip
    sc = small_section_scenario(
        tmp_path, net, routes, ["A", "B"], (red,),
        simulation={"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 1},
        instrumented={"ids": ["probe"]},
    )  # fmt: skip
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    traj = truth.trajectories[truth.trajectories["vehicle_id"] == "v0"]
    last = traj[traj["time_s"] == traj["time_s"].max()]
    sumo_stop = float(truth.section.lengths_m[0] - last["arc_m"].iloc[0])  # SUMO's own driver
    assert last["speed_mps"].iloc[0] < 0.01 and abs(sumo_stop - 3.0) < 0.05, sumo_stop
    act = prior_alone({**cross_krauss, "min_gap_m": FAR["minGap"]})
    core = DemandCore(sc, truth, truth.runs, 120)
    try:
        core.reset(int(truth.runs[0]), 0.5)
        assert core.vtypes["far"].stopline_gap_m == 3.0
        for _ in range(119):
            vids, obs = core.observe()
            res = core.step(act(obs))
            assert res.collisions == 0
        assert vids == ["v0"]
        dist = float(core.sim.stop_line_m("v0"))
        speed = core.lane_states()["v0"][2]
    finally:
        core.close()
    assert speed < 0.1, speed
    assert abs(dist - sumo_stop) < 0.15, (dist, sumo_stop)

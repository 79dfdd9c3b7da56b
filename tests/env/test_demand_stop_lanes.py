"""The demand env stops a car on a lane that does not lead its way where SUMO stops it.

game/cross, link 7 (1si_1, through) red and link 6 (1si_0, right) green all along: SUMO's
getNextTLS gives a car routed through on 1si_0 link 7's red, from 1si_1; SUMO's driver of
it, unable to change lanes, stands 0.00 m before its lane's end (``Simulation.stop_lines``'
``own``: False). The demand env drives the population with exact commands and no hand-over.
"""

from __future__ import annotations

from pathlib import Path

import sumo
from conftest import cross_program, prior_alone, small_section_scenario

from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.truth.section import load_section_truth, simulate_section

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
LENGTH_1SI = 135.75  # cross.net.xml's 1si lanes [m]


def test_the_demand_env_stops_a_through_car_on_a_turning_lane_at_the_lanes_end(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """One car routed through, on 1si's right-turn lane 0, lane changes off, driven by
    ``DemandCore`` with game/cross's Krauss prior alone (residual 0): it stands 0.0 m
    before the lane's end (within 0.15 m; measured 0.000 m), where SUMO's driver stands
    (0.00 m, ``tests/deploy/test_stop_line_lanes.py``). Before: 0.78 m (a standing
    leader at the through link's red less SUMO's 1 m, the prior's approach overshooting
    it by 0.2 m)."""
    red = cross_program(tmp_path, green=(6,))
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        "<routes>\n"
        '    <vehicle id="thr" depart="0" departSpeed="10" departLane="0" departPos="20">'
        '<route edges="1si 2o 2fo"/></vehicle>\n'
        '    <vehicle id="probe" depart="55"><route edges="1si 2o 2fo"/></vehicle>\n'
        "</routes>\n"
    )
    sc = small_section_scenario(
        tmp_path, CROSS, routes, ["1fi", "1si", "2o", "2fo"], (red,),
        simulation={"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 1},
        instrumented={"ids": ["probe"]},
    )  # fmt: skip
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    act = prior_alone(cross_krauss)
    core = DemandCore(sc, truth, truth.runs, 120)
    try:
        core.reset(int(truth.runs[0]), 0.5)
        for _ in range(119):
            vids, obs = core.observe()
            core.sim.set_lane_change_mode(vids, 0)
            res = core.step(act(obs))
            assert res.collisions == 0
        assert vids == ["thr"]
        lane, pos, speed, _ = core.lane_states()["thr"]
    finally:
        core.close()
    assert lane == "1si_0" and speed < 0.1, (lane, speed)
    assert abs(LENGTH_1SI - pos) < 0.15, LENGTH_1SI - pos

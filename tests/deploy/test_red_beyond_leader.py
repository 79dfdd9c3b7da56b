"""A driven car that stops for a yellow its leader passes: the safety layer holds it to its
own stop at the line, not only to the leader it follows.

The observation has one thing ahead, the nearer of the leader and the red (or yellow) line
(``observe_rows``, ``road.leaders.nearer_standing``), and the layer's safe speed was the
safe speed behind it. A leader that passes its yellow stays nearer than the line until it
crosses: its follower, which decided at the onset to stop (``deploy.yellow = "onset"``),
kept up with it and braked at 9-21 m/s^2 once the leader had crossed (drawn arterial 565,
run 1: 123 such brakings; with deploy.turns off and deploy.yellow stop the same approach
ended in a collision with a SUMO driver behind, hC44). SUMO's own driver takes the lesser
of both safe speeds; so does the layer now (``SectionSpeedDriver.drive``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import light_road, prior_alone, small_section_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import record_run


class Speeds(SectionSpeedDriver):
    """The deployment's driver, keeping each driven vehicle's speed at every step."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.speeds: dict[str, list[float]] = {}

    def drive(self, sim, vids, st) -> None:
        super().drive(sim, vids, st)
        for v in vids:
            self.speeds.setdefault(v, []).append(float(st.speed_mps[st.index[v]]))


def test_a_car_stopping_for_a_yellow_its_leader_passes_brakes_at_its_decel(
    tmp_path: Path, cross_krauss: dict
) -> None:
    """Two cars at 15 m/s, 25 m apart, into a light that turns yellow at 5 s (4 s, then
    red): the leader, 24 m before the line, cannot stop at 4.5 m/s^2 and passes; its
    follower, 49 m before it, can and stops. Both driven (the prior alone, the safety layer,
    the yellow decided at onset): the follower stands before the line and never brakes
    harder than its decel 4.5 m/s^2 (0.05 tolerance); before, it kept up with the leader
    and braked at about 9 m/s^2 once the leader had crossed. No collision."""
    net = light_road(tmp_path, 300.0, 200.0, 15.0)
    routes = tmp_path / "r.rou.xml"
    cars = "".join(
        f'    <vehicle id="{v}" depart="0" departSpeed="15" departPos="{pos}">'
        '<route edges="A B"/></vehicle>\n'
        for v, pos in (("lead", 200), ("follow", 175))
    )
    routes.write_text(f"<routes>\n{cars}</routes>\n")
    program = tmp_path / "tl.add.xml"
    program.write_text(
        '<additional>\n    <tlLogic id="tl" type="static" programID="gyr" offset="0">\n'
        '        <phase duration="5" state="G"/>\n        <phase duration="4" state="y"/>\n'
        '        <phase duration="10000" state="r"/>\n    </tlLogic>\n</additional>\n'
    )
    # The yellow at onset, the start rules and keep_clear off (stop 49 moved their defaults).
    old = {"yellow": "onset", "keep_clear": "off", "start_dawdle": 0.0, "start_reaction_s": 0.0}
    ids = {"ids": ["probe"]}
    sc = small_section_scenario(tmp_path, net, routes, ["A", "B"], instrumented=ids, deploy=old)
    assert sc.deploy.yellow == "onset"
    opts = SumoOptions(net, (program,), 0.5, 5, route_files=(routes,), user_demand=True)
    section = read_section(net, ["A", "B"], False)
    drv = Speeds(sc, section, 0, prior_alone(cross_krauss), "sumo")
    sim = Simulation(opts)
    try:
        _, stats = record_run(sim, sc, drv.section, 0, drv)
        line_m = float(sim.stop_lines_m(["follow"])[0])
    finally:
        sim.close()
    assert stats["collisions"] == 0
    lead, follow = np.array(drv.speeds["lead"]), np.array(drv.speeds["follow"])
    assert lead.min() > 10.0, lead  # it passed the yellow at speed
    assert follow[-1] < 0.1 and 0.0 < line_m < 2.0, (follow[-1], line_m)
    hardest = -np.diff(follow).min() / 0.5
    assert hardest < 4.55, (hardest, follow)

"""Cars from game/cross's 1fi to 2fo into a light that stays red, and a deployment driver
that keeps where each driven vehicle stood: shared by the stop-line tests of the
deployment (tests/deploy/test_stop_line_queue.py, test_prior_min_gap.py)."""

from __future__ import annotations

from pathlib import Path

import sumo
from conftest import one_phase_program, small_section_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
EDGES = ["1fi", "1si", "2o", "2fo"]


def red_light_queue(
    folder: Path, n_cars: int, duration_s: float
) -> tuple[SectionScenario, Simulation]:
    """``n_cars`` of SUMO's default vType departing every 2 s at 10 m/s from 1fi to 2fo,
    signal "0" red on every link all along, one probe instrumented (none of them), two runs
    of ``duration_s`` in two detector intervals: the scenario and run 0's simulation."""
    routes = folder / "r.rou.xml"
    cars = "".join(
        f'    <vehicle id="v{i}" depart="{2 * i}" departSpeed="10" departLane="best">'
        f'<route edges="{" ".join(EDGES)}"/></vehicle>\n'
        for i in range(n_cars)
    )
    routes.write_text(f"<routes>\n{cars}</routes>\n")
    red = one_phase_program(folder, "0", "r" * 12)
    sc = small_section_scenario(
        folder, CROSS, routes, EDGES, instrumented={"ids": ["probe"]},
        simulation={"warmup_s": 0.0, "duration_s": duration_s, "n_runs": 2},
        detectors={"interval_s": duration_s / 2},
    )  # fmt: skip
    options = SumoOptions(CROSS, (red,), 0.5, 5, route_files=(routes,), user_demand=True)
    return sc, Simulation(options)


class Standing(SectionSpeedDriver):
    """The deployment's driver, also keeping each driven vehicle's distance to the red line
    ahead (SUMO's, along its lane) and its speed at its last step."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.at: dict[str, tuple[float, float]] = {}  # vehicle: (distance to the line, speed)

    def drive(self, sim, vids, st) -> None:
        super().drive(sim, vids, st)
        for v, d in zip(vids, sim.stop_lines_m(vids), strict=True):
            self.at[v] = (float(d), float(st.speed_mps[st.index[v]]))

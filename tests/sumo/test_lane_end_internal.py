"""``Simulation.lane_end`` on a junction's internal lane: SUMO's best lanes there are the next
edge's (routes hold no internal edge), so the lane never has an end of its own: (inf, 0),
answered without asking SUMO; the lanes around it keep SUMO's answers."""

from __future__ import annotations

from pathlib import Path

import sumo

from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


def test_internal_lanes_have_no_lane_end_and_normal_lanes_keep_theirs(tmp_path: Path) -> None:
    """game/cross, its cycling signal: cars from 1fi turning right into 3o, and cars put on
    1si's right lane (1si_0) going straight on into 2o, which they must leave (through is
    1si_1's link); every vehicle asked every step. On internal lanes always (inf, 0); on
    1si_0 the through cars' lane end is finite (SUMO's answer, asked)."""
    routes = tmp_path / "r.rou.xml"
    cars = "".join(
        f'  <vehicle id="c{i:02d}" depart="{3 * i}" departSpeed="10" departLane="'
        + ('best"><route edges="1fi 1si 3o"/>' if i % 2 else '0"><route edges="1si 2o"/>')
        + "</vehicle>\n"
        for i in range(40)
    )
    routes.write_text(f"<routes>\n{cars}</routes>\n")
    sim = Simulation(SumoOptions(CROSS, (), 0.5, 3, route_files=(routes,), user_demand=True))
    internal, finite = 0, 0
    try:
        for _ in range(500):
            sim.step()
            st = sim.vehicle_states()
            for vid, lane, pos in zip(st.ids, st.lanes, st.pos_m.tolist(), strict=True):
                end, offset = sim.lane_end(vid, lane, pos)
                if lane.startswith(":"):
                    internal += 1
                    assert (end, offset) == (float("inf"), 0)
                elif end != float("inf"):
                    finite += 1
                    assert offset != 0 and end > -1.0
    finally:
        sim.close()
    assert internal > 100 and finite > 10  # 251 and 20

"""``Simulation.stop_lines``: the one query of the red lines ahead (the deployment's, the
demand env's and the snapshot env's), on real SUMO nets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import sumo

from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


def program(folder: Path, tls: str, state: str) -> Path:
    path = folder / "p.add.xml"
    path.write_text(
        f'<additional>\n    <tlLogic id="{tls}" type="static" programID="p" offset="0">\n'
        f'        <phase duration="10000" state="{state}"/>\n    </tlLogic>\n</additional>\n'
    )
    return path


def test_a_red_link_from_another_lane_is_not_the_vehicles_own(tmp_path: Path) -> None:
    """game/cross, link 7 (1si_1, through) red, link 6 (1si_0, right) green: SUMO gives
    "thr0" (through on 1si_0) and "thr1" (through on 1si_1) link 7's red at their lanes'
    end, "up" (through on 1fi, whose best lanes go on to 1si_1) too, 181.18 m ahead.
    Only thr0's is not its own: ``stop_lines_m`` is inf for it (it stops at its lane's
    end), the line itself for the others; "rgt" (right turn, link 6 green) has none."""
    state = ["r"] * 12
    state[6] = "G"
    sim = Simulation(SumoOptions(CROSS, (program(tmp_path, "0", "".join(state)),), 0.5, 1))
    ids = ["thr0", "thr1", "up", "rgt"]
    try:
        sim.add_route("thr", ["1si", "2o"])
        sim.add_route("upthr", ["1fi", "1si", "2o"])
        sim.add_route("rgt", ["1si", "3o"])
        places = [("thr", 0, 20.0), ("thr", 1, 20.0), ("upthr", 0, 5.0), ("rgt", 0, 60.0)]
        for vid, (route, lane, pos) in zip(ids, places, strict=True):
            sim.add_vehicle(vid, route, "DEFAULT_VEHTYPE", lane, pos, 10.0)
        sim.set_lane_change_mode(ids, 0)
        sim.step()
        lines = sim.stop_lines(ids)
        line_m = sim.stop_lines_m(ids)
        lanes, pos, _ = sim.lane_states(ids)
    finally:
        sim.close()
    assert lanes[:3] == ["1si_0", "1si_1", "1fi_0"]
    assert lines.lanes == ["1si_1", "1si_1", "1si_1", ""]
    assert lines.own.tolist()[:3] == [False, True, True]
    np.testing.assert_allclose(lines.dist_m[:2], 135.75 - pos[:2], atol=1e-6)
    assert lines.dist_m[3] == np.inf
    assert line_m[0] == np.inf and line_m[3] == np.inf
    np.testing.assert_array_equal(line_m[1:3], lines.dist_m[1:3])
    stop = lines.stop_m(1.0)
    assert stop[0] == np.inf and np.allclose(stop[1:3], lines.dist_m[1:3] - 1.0)

"""``Simulation.leaders`` answers ("", -1.0) for a vehicle without a leader whichever libsumo
function asks: the compiled ``vehicle_getLeader`` (no None to look for) and libsumo's Python
wrapper in traci's legacy mode, which says None (the scan for it is made only then)."""

from __future__ import annotations

from pathlib import Path

import libsumo
import pytest
import sumo

from macromicro_sumo.sumo import simulation
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


def test_no_leader_is_empty_with_the_compiled_function_and_the_legacy_wrapper(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """game/cross: two cars one behind the other on 1si; the first has no leader, the
    second the first. The same answers from both functions."""
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        "<routes>\n"
        + "".join(
            f'  <vehicle id="c{i}" depart="{2 * i}" departSpeed="5"><route edges="1si 2o"/>'
            "</vehicle>\n"
            for i in range(2)
        )
        + "</routes>\n"
    )
    sim = Simulation(SumoOptions(CROSS, (), 0.5, 3, route_files=(routes,), user_demand=True))
    try:
        for _ in range(8):
            sim.step()
        assert not simulation._LEADER_MAY_BE_NONE  # the compiled function is used
        compiled = sim.leaders(["c0", "c1"], 250.0)
        assert compiled[0] == ("", -1.0)
        assert compiled[1][0] == "c0" and compiled[1][1] > 0.0
        monkeypatch.setattr(libsumo.vehicle, "_legacyGetLeader", True)
        assert libsumo.vehicle.getLeader("c0", 250.0) is None  # what the wrapper says
        monkeypatch.setattr(simulation, "_GET_LEADER", libsumo.vehicle.getLeader)
        monkeypatch.setattr(simulation, "_LEADER_MAY_BE_NONE", True)
        assert sim.leaders(["c0", "c1"], 250.0) == compiled
    finally:
        sim.close()

"""``Simulation``'s once-a-vehicle answers of the stop-line query (``sumo.stop_lines``:
does a vehicle's lane carry it on to a red link's lane?) are kept only for vehicles still
in the network: a long run on a signalised net keeps no answers of vehicles gone."""

from __future__ import annotations

from pathlib import Path

import sumo

from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


def test_the_carry_answers_of_vehicles_gone_are_dropped(tmp_path: Path) -> None:
    """game/cross with its own cycling signal: cars every 2 s from 1fi through to 2fo,
    every vehicle's stop line asked every step. Cars on 1fi meet 1si's red link (another
    lane than theirs: an answer kept); at every step the answers held are of vehicles on
    the road alone, while more were kept over the run; removed vehicles' go too."""
    routes = tmp_path / "r.rou.xml"
    cars = "".join(
        f'  <vehicle id="c{i:03d}" depart="{2 * i}" departSpeed="10" departLane="best">'
        f'<route edges="1fi 1si 2o 2fo"/></vehicle>\n'
        for i in range(150)
    )
    routes.write_text(f"<routes>\n{cars}</routes>\n")
    sim = Simulation(SumoOptions(CROSS, (), 0.5, 3, route_files=(routes,), user_demand=True))
    kept_ever: set[str] = set()
    arrived = 0
    try:
        for _ in range(800):
            sim.step()
            arrived += len(sim.arrived())
            ids = sim.vehicle_ids()
            sim.stop_lines_m(ids)
            held = set(sim._lines.carry)
            kept_ever |= held
            assert held <= set(ids)
        assert held  # answers are kept while their vehicles drive
        gone = sorted(held)[:2]
        sim.remove_vehicles(gone)
        left = set(sim._lines.carry)
    finally:
        sim.close()
    assert arrived > 50  # 74
    assert len(kept_ever) > 50 > 2 * len(held)  # 65 kept over the run, 17 at its end
    assert not left & set(gone)

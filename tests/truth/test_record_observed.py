"""truth.section.record_run (stop 45, hS45): each vehicle's instrumented draw, taken after
the run from its departure's vType (no hash between SUMO's steps), is the draw per vehicle
in the frame and in the run's counts. Real SUMO: game/cross's own routes."""

from __future__ import annotations

from pathlib import Path

import sumo
from conftest import small_section_scenario

from macromicro_sumo.road.section import read_section
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import is_instrumented, record_run

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross"
EDGES = ["1fi", "1si", "2o", "2fo"]


def cross_sim(seed: int) -> Simulation:
    opts = SumoOptions(
        CROSS / "cross.net.xml", (), 1.0, seed, route_files=(CROSS / "cross.rou.xml",)
    )
    return Simulation(opts)


def test_the_observed_column_is_each_vehicles_draw_at_its_departure_vtype(
    tmp_path: Path,
) -> None:
    sc = small_section_scenario(
        tmp_path, CROSS / "cross.net.xml", CROSS / "cross.rou.xml", EDGES,
        instrumented={"penetration": 0.5},
        simulation={"warmup_s": 20.0, "duration_s": 200.0, "n_runs": 2},
    )  # fmt: skip
    sim = cross_sim(sc.seed + 1)
    try:
        df, stats = record_run(sim, sc, read_section(CROSS / "cross.net.xml", EDGES, False), 1)
    finally:
        sim.close()
    per_vehicle = df.groupby("vehicle_id").agg(vtype=("vtype", "first"), obs=("observed", "all"))
    assert len(per_vehicle) > 20 and df.groupby("vehicle_id")["observed"].nunique().max() == 1
    want = [
        is_instrumented(sc, v, t, 1)
        for v, t in zip(per_vehicle.index, per_vehicle.vtype, strict=True)
    ]
    assert per_vehicle["obs"].tolist() == want
    assert 0 < sum(want) < len(want)  # both kinds: the draw decides, not a constant
    assert stats["observed"] == sum(want) and stats["vehicles_seen"] == len(want)

"""Signalised arterials for the hidden-count bench (``bench_hidden_count.py --arterials``):
a main road of equal edges between fixed-time junctions (netconvert's programs), each with
a side street turning onto it, one turning off it and one crossing it; the queues at the
signals spill back from junction to junction. ``ARTERIALS`` 1 and 2 are the two that stop
33 measured (docs/sections-log.md, "The hidden count in queues"); any other number draws one
from that seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from macromicro_sumo.truth.vtype_spread import spread_routes


@dataclass(frozen=True)
class Arterial:
    """An arterial's layout and demand (veh/h, 0 .. 1200 s)."""

    junctions: int
    spacing_m: float  # between nodes along the main road
    lanes: int
    speed_mps: float
    main_vph: float  # cars along the whole main road
    truck_vph: float
    on_vph: float  # per junction: onto the main road from the north
    off_vph: float  # per junction: off it to the south
    across_vph: float  # per junction: south to north, across it
    seed: int  # SUMO's
    south_spacing_m: float | None = None  # the south nodes' spacing (None: ``spacing_m``)


ARTERIALS = {
    1: Arterial(3, 250.0, 2, 13.9, 1300.0, 100.0, 250.0, 200.0, 250.0, 7),
    # Stop 33 drew its south nodes 250 m apart, its junctions 200 m: kept to recreate it.
    2: Arterial(3, 200.0, 3, 16.7, 2000.0, 100.0, 150.0, 300.0, 250.0, 11, 250.0),
}


def draw_arterial(seed: int) -> Arterial:
    """An arterial drawn from ``seed``: 2-4 junctions 150-350 m apart, 1-3 lanes at 11-17
    m/s, 450-750 cars per lane and hour along it, 0-150 trucks, 100-300 turning on, off and
    across at each junction."""
    rng = np.random.default_rng(seed)
    lanes = int(rng.integers(1, 4))
    return Arterial(
        junctions=int(rng.integers(2, 5)),
        spacing_m=round(float(rng.uniform(150.0, 350.0))),
        lanes=lanes,
        speed_mps=round(float(rng.uniform(11.1, 16.7)), 1),
        main_vph=round(float(rng.uniform(450.0, 750.0)) * lanes),
        truck_vph=round(float(rng.uniform(0.0, 150.0))),
        on_vph=round(float(rng.uniform(100.0, 300.0))),
        off_vph=round(float(rng.uniform(100.0, 300.0))),
        across_vph=round(float(rng.uniform(100.0, 300.0))),
        seed=seed,
    )


def arterial(folder: Path, number: int, netconvert, spread: bool = False) -> tuple[dict, str]:
    """Arterial ``number`` (``ARTERIALS``, else drawn from it as a seed) in ``folder``: the
    scenario table (2 runs of 900 s after 120 s, loops every 100 m, 90 s intervals) and a
    description. ``netconvert(folder, name, nodes, edges)`` builds the net. ``spread``: each
    vType a seeded distribution of lengths and minGaps (``truth.vtype_spread``), so that
    standing queues do not sit on SUMO's 7.5 m lattice."""
    a = ARTERIALS.get(number) or draw_arterial(number)
    south = a.south_spacing_m or a.spacing_m
    n = a.junctions + 1
    names = ["a0", *(f"j{i}" for i in range(1, n)), f"a{n}"]
    nodes = ['<node id="a0" x="0" y="0"/>']
    edges = []
    for i in range(1, n):
        nodes += [
            f'<node id="j{i}" x="{a.spacing_m * i:g}" y="0" type="traffic_light"/>',
            f'<node id="n{i}" x="{a.spacing_m * i:g}" y="150"/>',
            f'<node id="s{i}" x="{south * i:g}" y="-150"/>',
        ]
        for eid, fr, to in (
            (f"n{i}j", f"n{i}", f"j{i}"),
            (f"jn{i}", f"j{i}", f"n{i}"),
            (f"s{i}j", f"s{i}", f"j{i}"),
            (f"js{i}", f"j{i}", f"s{i}"),
        ):
            edges.append(
                f'<edge id="{eid}" from="{fr}" to="{to}" numLanes="1" speed="13.9" priority="1"/>'
            )
    nodes.append(f'<node id="a{n}" x="{a.spacing_m * n:g}" y="0"/>')
    main = [f"m{i}" for i in range(n)]
    edges += [
        f'<edge id="m{i}" from="{names[i]}" to="{names[i + 1]}" numLanes="{a.lanes}" '
        f'speed="{a.speed_mps}" priority="2"/>'
        for i in range(n)
    ]
    net = netconvert(folder, "art", nodes, edges)
    flows = [("main", " ".join(main), a.main_vph, "car")]
    for i in range(1, n):
        flows += [
            (f"in{i}", f"n{i}j " + " ".join(main[i:]), a.on_vph, "car"),
            (f"off{i}", " ".join(main[:i]) + f" js{i}", a.off_vph, "car"),
            (f"x{i}", f"s{i}j jn{i}", a.across_vph, "car"),
        ]
    rows = [
        '<routes><vType id="car" length="5" minGap="2.5"/>'
        '<vType id="truck" length="12" minGap="2.5" vClass="truck" maxSpeed="25"/>'
    ]
    for f, route, vph, vtype in flows:
        rows.append(
            f'<route id="{f}" edges="{route}"/><flow id="{f}" type="{vtype}" route="{f}" '
            f'begin="0" end="1200" vehsPerHour="{vph:g}" departLane="best" departSpeed="max"/>'
        )
    if a.truck_vph > 0:  # on the main road's route
        rows.append(
            f'<flow id="tr" type="truck" route="main" begin="0" end="1200" '
            f'vehsPerHour="{a.truck_vph:g}" departLane="best" departSpeed="max"/>'
        )
    rows.append("</routes>")
    (folder / "art.rou.xml").write_text("".join(rows))
    if spread:
        spread_routes(folder / "art.rou.xml", folder / "art.rou.xml", a.seed)
    table = {
        "name": "arterial",
        "seed": a.seed,
        "network": {
            "kind": "sumo",
            "net_file": str(net),
            "route_files": [str(folder / "art.rou.xml")],
        },
        "section": {"edges": main, "closed": False},
        "instrumented": {"penetration": 0.1},
        "simulation": {"warmup_s": 120.0, "duration_s": 900.0, "n_runs": 2},
        "detectors": {"interval_s": 90.0, "auto_spacing_m": 100.0},
    }
    desc = (
        f"{a.junctions} signals {a.spacing_m:g} m apart, {a.lanes} lanes, {a.speed_mps} m/s, "
        f"{a.main_vph:g} + {a.truck_vph:g} trucks veh/h, side {a.on_vph:g} on / "
        f"{a.off_vph:g} off / {a.across_vph:g} across" + (", vTypes spread" if spread else "")
    )
    return table, desc

"""Two stations a few metres apart on a two-lane road, in real SUMO: the vehicles between
them are a possible count (``density.sealed_count``: one front per lane however short the
stretch). Their lane-metres / 5 m, the bound before stop 47, rejected such a pair, and with
it a whole arterial's exact count since the empty start (drawn 1161 and 1407: K 7.9 and 9.7
vehicles per lane off, counted 0.1)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import netconvert

from macromicro_sumo.truth.density import JAM_SPACING_M, sealed_count, stretch_room

GAP_M = 2.0  # the drawn arterials' closest stations: 1.8-4.2 m

RUN = """
import json, sys
import libsumo
libsumo.start(["sumo", "-n", sys.argv[1], "-r", sys.argv[2], "-a", sys.argv[3], "--seed", "3",
               "--no-step-log", "true", "--no-warnings", "true"])
entries = {}
for _ in range(1200):  # 600 s at 0.5 s
    libsumo.simulationStep()
    for loop in libsumo.inductionloop.getIDList():
        for veh, _, entry, _, _ in libsumo.inductionloop.getVehicleData(loop):
            if entry >= 0:
                entries.setdefault(loop, {})[veh] = entry
libsumo.close()
print(json.dumps(entries))
"""


def passages(tmp_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The front passages at the upstream station (loops at 150 m on both lanes) and at the
    downstream one (``GAP_M`` further), 1800 vehicles/h towards a red light at 290 m."""
    net = netconvert(
        tmp_path,
        '<node id="a" x="0" y="0"/><node id="b" x="300" y="0" type="traffic_light"/>'
        '<node id="c" x="400" y="0"/>',
        '<edge id="e0" from="a" to="b" numLanes="2" speed="14"/>'
        '<edge id="e1" from="b" to="c" numLanes="2" speed="14"/>',
        extra=("--tls.cycle.time", "60"),
    )
    (tmp_path / "r.rou.xml").write_text(
        '<routes><vType id="car" length="5" minGap="2.5" sigma="0"/>'
        '<flow id="f" type="car" from="e0" to="e1" begin="0" end="500" vehsPerHour="1800" '
        'departLane="free" departSpeed="max"/></routes>'
    )
    loops = "".join(
        f'<inductionLoop id="{name}_{lane}" lane="e0_{lane}" pos="{pos}" period="60" file="NUL"/>'
        for name, pos in (("up", 150.0), ("down", 150.0 + GAP_M))
        for lane in (0, 1)
    )
    (tmp_path / "loops.add.xml").write_text(f"<additional>{loops}</additional>")
    out = subprocess.run(
        [sys.executable, "-c", RUN, str(net), str(tmp_path / "r.rou.xml"), "loops.add.xml"],
        cwd=tmp_path,
        check=True,
        capture_output=True,
        text=True,
    )
    entries = json.loads(out.stdout.strip().splitlines()[-1])

    def station(name: str) -> np.ndarray:
        """Each vehicle once, at its first loop (``stations.station_passages``: one that
        changes lane over the loops is seen by both)."""
        first: dict[str, float] = {}
        for lane in (0, 1):
            for veh, t in entries[f"{name}_{lane}"].items():
                first[veh] = min(t, first.get(veh, t))
        return np.sort(list(first.values()))

    return station("up"), station("down")


def test_two_stations_metres_apart_hold_a_possible_count(tmp_path: Path) -> None:
    up, down = passages(tmp_path)
    # Nobody enters or leaves between them; at the end one may stand there.
    assert len(up) > 100 and 0 <= len(up) - len(down) <= 2
    t = np.concatenate([up, down])
    step = np.concatenate([np.ones(len(up)), -np.ones(len(down))])
    n = np.cumsum(step[np.lexsort((-step, t))])
    # Vehicles do stand between them (the queue at red), more than the lane-metres allow.
    assert n.max() >= 1 and n.max() > 2 * GAP_M / JAM_SPACING_M, n.max()
    assert n.max() <= stretch_room(GAP_M, 2) == 2
    assert sealed_count(up, down, GAP_M, 2)
    # One more vehicle out than in (a departure between them): impossible, rejected.
    assert not sealed_count(up[1:], down, GAP_M, 2)

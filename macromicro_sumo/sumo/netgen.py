"""Random one-way corridors: SUMO networks nobody has seen, for testing the general path.

The ring of the paper was hand-built; a corridor drawn from a seed checks that nothing in the
pipeline silently depends on that ring (edge names, one lane, equal lengths, one vType).
The network is written as SUMO plain XML and built by netconvert rather than netgenerate:
netgenerate's grid cannot give each edge its own length, lane count and speed limit.
"""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sumolib

from macromicro_sumo.errors import UserError

EDGE_LENGTH_RANGE_M = (250.0, 600.0)
"""Edge lengths drawn uniformly in this range [m]."""
SPEED_RANGE_MPS = (20.0, 36.0)
"""Speed limits drawn uniformly in this range [m/s], rounded to 0.01."""
LANES_RANGE = (1, 3)
"""Lane counts per edge drawn uniformly from this inclusive range; they may change per edge."""
FLOW_PER_LANE_RANGE_VPH = (600.0, 1100.0)
"""Demand drawn per lane of the narrowest edge [veh/h]: well below capacity, so the corridor
carries free-flowing traffic (about 8-15 vehicles per km and lane of the narrowest edge)
rather than a standing queue behind a lane drop."""


@dataclass(frozen=True)
class Corridor:
    """A generated corridor: its files and the section, edges in driving order.

    ``lengths_m`` are the built lane lengths (netconvert shortens the drawn node distances by
    the junction shapes), ``speeds_mps`` the edges' limits.
    """

    net_file: Path
    routes_file: Path
    sumocfg: Path
    section_edges: tuple[str, ...]
    lanes_per_edge: tuple[int, ...]
    lengths_m: tuple[float, ...]
    speeds_mps: tuple[float, ...]
    vehs_per_hour: float


def _netconvert(nodes: Path, edges: Path, out: Path) -> None:
    """Build ``out`` from plain XML; straight joins, no turnarounds, fixed precision."""
    cmd = [
        sumolib.checkBinary("netconvert"),
        "--node-files", str(nodes),
        "--edge-files", str(edges),
        "--output-file", str(out),
        "--no-turnarounds", "true",
        "--precision", "3",
        "--no-warnings", "true",
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise UserError(f"netconvert failed for {out}: {done.stderr.strip()}")
    # The header comment carries the date and absolute input paths: drop it so that one seed
    # gives the same bytes wherever and whenever it is built.
    text = out.read_text()
    out.write_text(re.sub(r"<!--.*?-->\s*", "", text, count=1, flags=re.S))


def random_corridor(
    out_dir: Path,
    seed: int,
    n_edges: int | None = None,
    name: str = "corridor",
    end_s: float = 86400.0,
) -> Corridor:
    """Draw and build a one-way corridor with its demand in ``out_dir``; same seed, same bytes.

    ``n_edges`` edges (4-7 if None) with random lengths, lane counts and speed limits, one
    flow per vType (an IDM car of 4.5 m and a Krauss car of 5.0 m, both with explicit length)
    over the whole corridor until ``end_s``. The section is every edge, in driving order.
    """
    rng = np.random.default_rng(seed)
    n = int(rng.integers(4, 8)) if n_edges is None else int(n_edges)
    if n < 1:
        raise UserError(f"random_corridor: n_edges={n_edges}; accepted: >= 1")
    lengths = np.round(rng.uniform(*EDGE_LENGTH_RANGE_M, size=n), 1)
    lanes = rng.integers(LANES_RANGE[0], LANES_RANGE[1] + 1, size=n)
    speeds = np.round(rng.uniform(*SPEED_RANGE_MPS, size=n), 2)
    vph = float(np.round(rng.uniform(*FLOW_PER_LANE_RANGE_VPH) * lanes.min()))
    share_idm = float(np.round(rng.uniform(0.3, 0.7), 2))

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    x = np.concatenate([[0.0], np.cumsum(lengths)])
    edges = tuple(f"e{i}" for i in range(n))
    nodes_xml = ["<nodes>"]
    nodes_xml += [f'    <node id="n{i}" x="{xi:.1f}" y="0.0"/>' for i, xi in enumerate(x)]
    nodes_xml.append("</nodes>")
    edges_xml = ["<edges>"]
    for i, eid in enumerate(edges):
        edges_xml.append(
            f'    <edge id="{eid}" from="n{i}" to="n{i + 1}" numLanes="{lanes[i]}" '
            f'speed="{speeds[i]:.2f}" spreadType="center"/>'
        )
    edges_xml.append("</edges>")
    nodes_file = out_dir / f"{name}.nod.xml"
    edges_file = out_dir / f"{name}.edg.xml"
    nodes_file.write_text("\n".join(nodes_xml) + "\n")
    edges_file.write_text("\n".join(edges_xml) + "\n")
    net_file = out_dir / f"{name}.net.xml"
    _netconvert(nodes_file, edges_file, net_file)
    nodes_file.unlink()
    edges_file.unlink()

    routes_file = out_dir / f"{name}.rou.xml"
    route = " ".join(edges)
    routes_file.write_text(
        "<routes>\n"
        '    <vType id="car_idm" length="4.5" minGap="2.0" carFollowModel="IDM" accel="1.5" '
        'decel="3.0" tau="1.2" delta="4" speedFactor="1.0" speedDev="0.1"/>\n'
        '    <vType id="car_krauss" length="5.0" minGap="2.5" carFollowModel="Krauss" '
        'accel="2.6" decel="4.5" sigma="0.5" tau="1.0" speedFactor="1.0" speedDev="0.1"/>\n'
        f'    <route id="corridor" edges="{route}"/>\n'
        f'    <flow id="f_idm" type="car_idm" route="corridor" begin="0" end="{end_s:g}" '
        f'vehsPerHour="{vph * share_idm:.1f}" departLane="best" departSpeed="desired"/>\n'
        f'    <flow id="f_krauss" type="car_krauss" route="corridor" begin="0" end="{end_s:g}" '
        f'vehsPerHour="{vph * (1 - share_idm):.1f}" departLane="best" departSpeed="desired"/>\n'
        "</routes>\n"
    )
    net = sumolib.net.readNet(str(net_file))
    sumocfg = out_dir / f"{name}.sumocfg"
    sumocfg.write_text(
        "<sumoConfiguration>\n"
        "    <input>\n"
        f'        <net-file value="{net_file.name}"/>\n'
        f'        <route-files value="{routes_file.name}"/>\n'
        "    </input>\n"
        "</sumoConfiguration>\n"
    )
    return Corridor(
        net_file=net_file,
        routes_file=routes_file,
        sumocfg=sumocfg,
        section_edges=edges,
        lanes_per_edge=tuple(int(k) for k in lanes),
        lengths_m=tuple(round(net.getEdge(e).getLength(), 3) for e in edges),
        speeds_mps=tuple(float(v) for v in speeds),
        vehs_per_hour=vph,
    )

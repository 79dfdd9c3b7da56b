"""Ring networks: build an exact circle with netconvert (``road.section`` reads it).

The ring is a single lane of length exactly 2 pi R, split into edges ``e0 .. e{n-1}`` so
that speed limits can be piecewise constant. Vehicles circulate forever through one-lap
routes ``r_eI`` and a rerouter on every edge (see shared/notes/sumo-ring-facts.md).
"""

from __future__ import annotations

import math
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import sumolib

NETCONVERT_ARGS = [
    # Without these the lane moves outward, junctions add internal lanes and lengths are
    # rounded: the ring silently stops being 2 pi R long.
    "--no-internal-links",
    "true",
    "--no-turnarounds",
    "true",
    "--junctions.corner-detail",
    "0",
    "--precision",
    "6",
]


def build_ring(
    radius_m: float,
    n_edges: int,
    out_dir: Path,
    name: str,
    speed_mps: float = 13.89,
    lanes: int = 1,
) -> tuple[Path, Path]:
    """Write ``<name>.net.xml`` (exact ring, ``lanes`` lanes; the centre line is the
    circle) and ``<name>.add.xml`` (routes + rerouters)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    edge_len = 2 * math.pi * radius_m / n_edges
    angles = [2 * math.pi * k / n_edges for k in range(n_edges)]
    nodes = "\n".join(
        f'    <node id="n{k}" x="{radius_m * math.cos(a):.6f}" y="{radius_m * math.sin(a):.6f}"/>'
        for k, a in enumerate(angles)
    )
    edges = []
    for k in range(n_edges):
        k2 = (k + 1) % n_edges
        # Intermediate shape points trace the arc (only for drawing; length is explicit).
        shape = []
        for j in range(17):
            a = 2 * math.pi * (k + j / 16) / n_edges
            shape.append(f"{radius_m * math.cos(a):.6f},{radius_m * math.sin(a):.6f}")
        edges.append(
            f'    <edge id="e{k}" from="n{k}" to="n{k2}" numLanes="{lanes}" speed="{speed_mps}" '
            f'length="{edge_len:.6f}" spreadType="center" shape="{" ".join(shape)}"/>'
        )
    net_path = out_dir / f"{name}.net.xml"
    with tempfile.TemporaryDirectory() as tmp:
        nod = Path(tmp) / "ring.nod.xml"
        edg = Path(tmp) / "ring.edg.xml"
        nod.write_text(f"<nodes>\n{nodes}\n</nodes>\n")
        edg.write_text("<edges>\n" + "\n".join(edges) + "\n</edges>\n")
        cmd = [
            sumolib.checkBinary("netconvert"),
            "--node-files",
            str(nod),
            "--edge-files",
            str(edg),
            "--output-file",
            str(net_path),
            *NETCONVERT_ARGS,
        ]
        subprocess.run(cmd, check=True, capture_output=True, text=True)
    add_path = out_dir / f"{name}.add.xml"
    add_path.write_text(ring_routes_xml(n_edges))
    return net_path, add_path


def ring_routes_xml(n_edges: int) -> str:
    """One-lap routes per start edge, then a rerouter per edge that restarts the lap."""
    routes = []
    rerouters = []
    for k in range(n_edges):
        lap = " ".join(f"e{(k + j) % n_edges}" for j in range(n_edges + 1))
        routes.append(f'    <route id="r_e{k}" edges="{lap}"/>')
        rerouters.append(
            f'    <rerouter id="rr_e{k}" edges="e{k}">\n'
            f'        <interval begin="0" end="1e9"><routeProbReroute id="r_e{k}"/></interval>\n'
            f"    </rerouter>"
        )
    # Routes must come before the rerouters that name them.
    return "<additional>\n" + "\n".join(routes + rerouters) + "\n</additional>\n"


def loop_successors(s: np.ndarray, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """On a closed one-lane loop (the ring): each item's next one round the loop and the arc
    to it, for positions ``s`` in [0, length): one sort, where the lane-connection walk of
    ``section_leaders`` loops over the edges in Python (a quarter of a ring run's time).
    Equal positions keep their index order; a lone item's next is itself, a lap ahead."""
    order = np.argsort(s, kind="stable")
    nxt = np.empty(len(s), dtype=np.int64)
    nxt[order] = np.roll(order, -1)
    ordered = s[order]
    gap = np.empty(len(s))
    gap[order[:-1]] = np.diff(ordered)
    gap[order[-1]] = ordered[0] + length_m - ordered[-1]
    return nxt, gap

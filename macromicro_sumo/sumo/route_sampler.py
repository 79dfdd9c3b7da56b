"""A demand from station counts with SUMO's own ``routeSampler.py`` (sumo/tools, shipped in
the eclipse-sumo wheel), for a user who has field stations but no route files.

routeSampler picks routes from a set of candidates and departure times so that the number
of vehicles entering each counting edge in each interval matches the counts (with
``--optimize full``: a linear program, so counts that fit together are met exactly).
The candidates are built here from the network (``candidate_routes``): every way onto the
section (its first edge, each on-ramp) combined with every way off it (its last edge, each
off-ramp), each extended upstream by a short run-up so that vehicles enter the section at
speed. routeSampler runs as a subprocess of this Python (``sys.executable``), so its
sumolib is the one this package imports; its one-line failures become ``UserError``.
Everything here is plain XML and files: ``sumo.simulation`` stays the one libsumo importer.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

import sumo
import sumolib

from macromicro_sumo.errors import UserError

ROUTE_SAMPLER = Path(sumo.SUMO_HOME) / "tools" / "routeSampler.py"
RUN_UP_M = 300.0  # upstream edges added before an entry, so vehicles merge at speed
MAX_ROUTES = 500  # candidates beyond this are a network too meshed for this heuristic
VCLASS = "passenger"


def _usable(edge: sumolib.net.edge.Edge) -> bool:
    return edge.getFunction() != "internal" and edge.allows(VCLASS)


def _run_up(edge: sumolib.net.edge.Edge, avoid: set[str]) -> list[str]:
    """``edge`` and the single-predecessor chain before it, up to ``RUN_UP_M`` of road."""
    path, length = [edge.getID()], edge.getLength()
    while length < RUN_UP_M:
        before = [e for e in edge.getIncoming() if _usable(e) and e.getID() not in avoid]
        if len(before) != 1 or before[0].getID() in path:
            break
        edge = before[0]
        path.insert(0, edge.getID())
        length += edge.getLength()
    return path


def candidate_routes(net_file: Path, section_edges: Sequence[str]) -> list[list[str]]:
    """Every route that drives on the section: entered at its first edge (after a run-up)
    or from an on-ramp into edge i, left at its last edge or by an off-ramp after edge j
    (j >= i). ``section_edges`` are consecutive edges of the network in driving order."""
    net = sumolib.net.readNet(str(net_file))
    edges = [net.getEdge(e) for e in section_edges]
    on_section = set(section_edges)
    last = len(edges) - 1
    # (section edge entered, the edges driven before it)
    entries: list[tuple[int, list[str]]] = [(0, _run_up(edges[0], on_section)[:-1])]
    exits: list[tuple[int, list[str]]] = [(last, [])]  # (last section edge, edges after it)
    for i, e in enumerate(edges):
        if i > 0:
            entries += [
                (i, _run_up(b, on_section))
                for b in e.getIncoming()
                if _usable(b) and b.getID() not in on_section
            ]
        if i < last:
            exits += [
                (i, [a.getID()])
                for a in e.getOutgoing()
                if _usable(a) and a.getID() not in on_section
            ]
    routes = [
        before + list(section_edges[i : j + 1]) + after
        for i, before in entries
        for j, after in exits
        if j >= i
    ]
    if len(routes) > MAX_ROUTES:
        raise UserError(
            f"{net_file}: {len(routes)} ways on and off the section; at most {MAX_ROUTES} "
            "are sampled from (give the scenario route files instead)"
        )
    return routes


def routes_xml(routes: Sequence[Sequence[str]]) -> str:
    """A route file with the candidates (``c0``, ``c1``, ...)."""
    rows = [f'    <route id="c{i}" edges="{" ".join(r)}"/>' for i, r in enumerate(routes)]
    return "<routes>\n" + "\n".join(rows) + "\n</routes>\n"


def edge_counts_xml(intervals: Sequence[tuple[float, float, Mapping[str, int]]]) -> str:
    """An edgeData file (``entered``: vehicles entering the edge) with one
    ``(begin_s, end_s, {edge: count})`` per interval: routeSampler's counting input."""
    rows = ["<data>"]
    for k, (begin, end, counts) in enumerate(intervals):
        rows.append(f'    <interval id="i{k}" begin="{begin:g}" end="{end:g}">')
        rows += [
            f'        <edge id={quoteattr(e)} entered="{int(n)}"/>'
            for e, n in sorted(counts.items())
        ]
        rows.append("    </interval>")
    rows.append("</data>")
    return "\n".join(rows) + "\n"


def sample_routes(
    routes_file: Path,
    counts_file: Path,
    out_file: Path,
    seed: int,
    prefix: str,
    attributes: str,
) -> Path:
    """``routeSampler.py -r routes_file -d counts_file -o out_file --optimize full``:
    vehicles (ids ``prefix`` + number, ``attributes`` on each) whose routes and departure
    times meet the counts; ``seed`` fixes its draws. UserError with routeSampler's last
    message line if it fails."""
    cmd = [
        sys.executable,
        str(ROUTE_SAMPLER),
        "-r",
        str(routes_file),
        "-d",
        str(counts_file),
        "-o",
        str(out_file),
        "--optimize",
        "full",
        "-s",
        str(int(seed)),
        "--prefix",
        prefix,
        "-a",
        attributes,
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0 or not out_file.is_file():
        lines = (done.stderr or done.stdout).strip().splitlines() or ["no output"]
        raise UserError(f"{counts_file}: routeSampler.py failed: {lines[-1]}")
    return out_file

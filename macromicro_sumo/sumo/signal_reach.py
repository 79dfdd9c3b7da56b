"""Which lanes of a network can have a signal ahead: those of the edges from which some
signalised link (a net file ``<connection>`` with a ``tl``) can be reached along the
network's connections. SUMO's getNextTLS (``Simulation.stop_lines``) reports only links met
along a vehicle's lanes and route, so a vehicle on any other lane has none ahead, whatever
its route, lane changes or best lanes: a driver need not ask (``deploy.drivers``; on
Bremen's section no lane reaches the ramp's signal, and the query was ~23 us a step).

Edges, not lanes: a vehicle may change to any lane of its edge, so an edge reaches a signal
where any of its lanes does. Internal (junction) edges are followed through their own
connections. The net file is read once per file and process, again where it changed.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections import defaultdict

from macromicro_sumo.sumo.net_xml import once_per_file, open_net


@once_per_file
def signal_lanes(net_file: str) -> frozenset[str]:
    """The lane IDs (internal lanes included) of ``net_file``'s edges from which a
    signalised link can be reached; empty where the network has no signal."""
    lanes: dict[str, list[str]] = defaultdict(list)  # edge -> its lanes
    before: dict[str, set[str]] = defaultdict(set)  # edge -> the edges that lead onto it
    signalised: set[str] = set()  # edges with a signalised link
    edge = ""
    with open_net(net_file) as fh:
        for event, el in ET.iterparse(fh, events=("start", "end")):
            if event == "start":
                if el.tag == "edge":
                    edge = el.get("id", "")
                elif el.tag == "lane" and edge:
                    lanes[edge].append(el.get("id", ""))
                continue
            if el.tag == "edge":
                edge = ""
            elif el.tag == "connection":
                src, dst, via = el.get("from", ""), el.get("to", ""), el.get("via")
                before[dst].add(src)
                if via:  # the junction's internal lane: its edge lies between
                    inner = via.rpartition("_")[0]
                    before[inner].add(src)
                    before[dst].add(inner)
                if el.get("tl"):
                    signalised.add(src)
            if el.tag in ("edge", "connection", "tlLogic", "junction"):
                el.clear()
    reach, todo = set(signalised), list(signalised)
    while todo:
        for prev in before[todo.pop()] - reach:
            reach.add(prev)
            todo.append(prev)
    return frozenset(ln for e in reach for ln in lanes.get(e, ()))

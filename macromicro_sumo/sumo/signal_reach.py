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

from collections import defaultdict

from macromicro_sumo.sumo.net_xml import net_links, once_per_file


@once_per_file
def signal_lanes(net_file: str) -> frozenset[str]:
    """The lane IDs (internal lanes included) of ``net_file``'s edges from which a
    signalised link can be reached; empty where the network has no signal."""
    net = net_links(net_file)
    before: dict[str, set[str]] = defaultdict(set)  # edge -> the edges that lead onto it
    signalised: set[str] = set()  # edges with a signalised link
    for c in net.connections:
        before[c.dst].add(c.src)
        if c.via:  # the junction's internal lane: its edge lies between
            inner = c.via.rpartition("_")[0]
            before[inner].add(c.src)
            before[c.dst].add(inner)
        if c.tl:
            signalised.add(c.src)
    reach, todo = set(signalised), list(signalised)
    while todo:
        for prev in before[todo.pop()] - reach:
            reach.add(prev)
            todo.append(prev)
    return frozenset(ln for e in reach for ln in net.lanes.get(e, ()))

"""A network's ``<stopOffset>``s: SUMO's drivers stop that far before a lane's end at a red or
yellow light (at least their vType's jmStoplineGap), for the vehicle classes it names.

Neither libsumo nor sumolib (1.28) reads them, so the net file is: an edge's stopOffset holds
for each of its lanes without one of its own; a lane's replaces the edge's (measured, SUMO
1.28: a bus on a lane whose own stopOffset names only passenger cars stops at the line less
its jmStoplineGap, not at the edge's offset).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

from macromicro_sumo.sumo.net_xml import once_per_file, open_net


@dataclass(frozen=True)
class StopOffset:
    value_m: float
    classes: frozenset[str] | None  # None: every vehicle class
    exceptions: frozenset[str]

    def applies(self, vehicle_class: str) -> bool:
        inside = self.classes is None or vehicle_class in self.classes
        return inside and vehicle_class not in self.exceptions


def _offset(attrs: dict[str, str]) -> StopOffset:
    classes = attrs.get("vClasses", "all").split()
    return StopOffset(
        float(attrs.get("value", 0.0)),
        None if "all" in classes or not classes else frozenset(classes),
        frozenset(attrs.get("exceptions", "").split()),
    )


@once_per_file
def lane_stop_offsets(net_file: str) -> dict[str, StopOffset]:
    """{lane ID: its stopOffset} of the lanes of ``net_file`` that have one (their own or
    their edge's); read once per file and process, again where the file changed."""
    out: dict[str, StopOffset] = {}
    stack: list[ET.Element] = []
    edge_offset: StopOffset | None = None
    lanes: list[str] = []  # the current edge's lanes without an offset of their own
    with open_net(net_file) as fh:
        for event, el in ET.iterparse(fh, events=("start", "end")):
            if event == "start":
                stack.append(el)
                if el.tag == "edge":
                    edge_offset, lanes = None, []
                continue
            stack.pop()
            parent = stack[-1].tag if stack else ""
            if el.tag == "stopOffset":
                if parent == "lane":
                    out[stack[-1].get("id", "")] = _offset(dict(el.attrib))
                elif parent == "edge":
                    edge_offset = _offset(dict(el.attrib))
            elif el.tag == "lane" and parent == "edge":
                lanes.append(el.get("id", ""))
            elif el.tag == "edge":
                if edge_offset is not None:
                    out.update((ln, edge_offset) for ln in lanes if ln not in out)
                el.clear()
            elif parent == "net":
                el.clear()
    return out

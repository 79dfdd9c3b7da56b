"""B disjoint copies of a SUMO network in one net file (pure XML, no SUMO run).

The batched env core (``env/batched.py``) steps B independent scenes in one SUMO
simulation: scene b drives on copy b, whose every ID (edges, lanes, junctions,
connections, signals) carries the prefix ``copy_prefix(b)``. The copies are the original
elements duplicated as they are, lengths, speeds and junction logic included, and only
shifted sideways in the drawing: netconvert is not run again, since it would recompute
lengths and shapes from coordinates and a copy could then differ from the original by a
rounding (``read_section`` on a copy gives the original's offsets exactly; tested).
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

from macromicro_sumo.errors import UserError

# Attributes holding one ID, and those holding a space-separated list of IDs, per element.
_ID_ATTRS = {
    "edge": ("id", "from", "to"),
    "lane": ("id",),
    "junction": ("id",),
    "connection": ("from", "to", "via", "tl"),
    "tlLogic": ("id",),
    "neigh": ("lane",),
}
_ID_LIST_ATTRS = {"junction": ("incLanes", "intLanes"), "roundabout": ("nodes", "edges")}
_SHAPE_ATTRS = ("shape", "customShape")
# Elements of the net a copy repeats; the rest (location, edge types) stays once.
_COPIED = ("edge", "junction", "connection", "tlLogic", "roundabout")
GAP_M = 100.0  # space between copies in the drawing [m]


def copy_prefix(b: int) -> str:
    """The ID prefix of copy ``b`` (an internal ID ``:x`` becomes ``:<prefix>x``)."""
    return f"c{b}_"


def copy_id(b: int, sumo_id: str) -> str:
    """``sumo_id`` (an edge, lane, junction or signal of the original) in copy ``b``."""
    p = copy_prefix(b)
    return f":{p}{sumo_id[1:]}" if sumo_id.startswith(":") else f"{p}{sumo_id}"


def _shift(shape: str, dx: float) -> str:
    pts = []
    for xy in shape.split():
        c = xy.split(",")
        pts.append(",".join([f"{float(c[0]) + dx:.6f}", *c[1:]]))
    return " ".join(pts)


def _rename(el: ET.Element, b: int, dx: float) -> None:
    for a in _ID_ATTRS.get(el.tag, ()):
        if el.get(a):
            el.set(a, copy_id(b, el.get(a, "")))
    for a in _ID_LIST_ATTRS.get(el.tag, ()):
        if el.get(a):
            el.set(a, " ".join(copy_id(b, x) for x in el.get(a, "").split()))
    for a in _SHAPE_ATTRS:
        if el.get(a):
            el.set(a, _shift(el.get(a, ""), dx))
    if el.tag == "junction" and el.get("x") is not None:
        el.set("x", f"{float(el.get('x', '0')) + dx:.6f}")
    for child in el:
        _rename(child, b, dx)


def tile_net(net_file: Path, copies: int, out_file: Path) -> Path:
    """Write ``copies`` disjoint copies of ``net_file`` into ``out_file``; returns it."""
    if copies < 1:
        raise UserError(f"tile_net: copies = {copies}: at least 1")
    try:
        tree = ET.parse(net_file)
    except (OSError, ET.ParseError) as exc:
        raise UserError(f"{net_file}: not a readable SUMO network ({exc})") from None
    root = tree.getroot()
    if root.tag != "net":
        raise UserError(f"{net_file}: not a SUMO network (root <{root.tag}>)")
    originals = [el for el in root if el.tag in _COPIED]
    xs = [
        float(xy.split(",")[0])
        for el in root.iter()
        for a in _SHAPE_ATTRS
        if el.get(a)
        for xy in el.get(a, "").split()
    ]
    width = (max(xs) - min(xs) if xs else 0.0) + GAP_M
    for el in originals:
        root.remove(el)
    for el in originals:  # the original's order of elements (edges before junctions ...)
        for b in range(copies):
            c = copy.deepcopy(el)
            _rename(c, b, b * width)
            root.append(c)
    out_file = Path(out_file)
    tree.write(out_file, encoding="UTF-8", xml_declaration=True)
    return out_file

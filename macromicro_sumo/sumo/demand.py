"""The demand of a user's own SUMO files, checked before any simulation starts: its vehicle
types (lengths and minGaps, with SUMO's defaults per ``vClass``), that its routes, vehicles,
trips and flows use only edges of the network, the ring's routes and rerouters, and that
instrumented vehicle ids name vehicles of the demand. Every problem is a one-line
``UserError`` naming the file, the element and the value.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import sumolib

from macromicro_sumo.errors import UserError
from macromicro_sumo.sumo.inputs import SumoInputs, local_tag, top_elements

DEFAULT_VEHTYPE = "DEFAULT_VEHTYPE"
"""SUMO's implicit vType for vehicles without ``type=``: passenger, length 5 m, minGap 2.5 m,
Krauss (https://sumo.dlr.de/docs/Definition_of_Vehicles%2C_Vehicle_Types%2C_and_Routes.html)."""

VCLASS_DEFAULTS: dict[str, tuple[float, float]] = {
    "pedestrian": (0.215, 0.25),
    "bicycle": (1.6, 0.5),
    "wheelchair": (1.2, 0.5),
    "scooter": (1.2, 0.5),
    "moped": (2.1, 2.5),
    "motorcycle": (2.2, 2.5),
    "drone": (0.5, 2.5),
    "delivery": (6.5, 2.5),
    "emergency": (6.5, 2.5),
    "container": (6.096, 2.5),
    "truck": (7.1, 2.5),
    "bus": (12.0, 2.5),
    "coach": (14.0, 2.5),
    "trailer": (16.5, 2.5),
    "ship": (17.0, 2.5),
    "tram": (22.0, 2.5),
    "aircraft": (72.7, 2.5),
    "rail_urban": (109.5, 5.0),
    "subway": (109.5, 5.0),
    "rail": (135.0, 5.0),
    "rail_electric": (200.0, 5.0),
    "rail_fast": (200.0, 5.0),
}
"""SUMO's (length, minGap) in m of a vType that sets its ``vClass`` but not these, as SUMO
1.28 reports them (``vehicletype.getLength``); every other class, and a vType without
``vClass`` (a passenger car), gets ``VCLASS_DEFAULT``."""
VCLASS_DEFAULT = (5.0, 2.5)

_VEHICLE_TAGS = ("vehicle", "flow", "trip")
_NOT_PARAMS = {"id", "length", "minGap", "carFollowModel", "vClass", "color", "guiShape"}


@dataclass(frozen=True)
class VType:
    """A vehicle type as the user's files define it (only what the method needs)."""

    id: str
    length_m: float
    min_gap_m: float
    car_follow_model: str
    params: dict[str, float] = field(default_factory=dict)


def _vtype_from_xml(elem: ET.Element, file: Path) -> VType | str:
    """A VType, or the reason it cannot be used (a bad length or minGap). A missing length or
    minGap is SUMO's default for the vType's ``vClass`` (``VCLASS_DEFAULTS``)."""
    tid = elem.get("id", "")
    default_length, default_gap = VCLASS_DEFAULTS.get(elem.get("vClass", ""), VCLASS_DEFAULT)
    length = elem.get("length", repr(default_length))
    try:
        length_m = float(length)
    except ValueError:
        length_m = math.nan
    if not (length_m > 0 and math.isfinite(length_m)):
        return f"{file}: vType '{tid}' has length '{length}'; accepted: length > 0 in m"
    model = elem.get("carFollowModel", "")
    params: dict[str, float] = {}
    for child in elem:
        ctag = local_tag(child.tag)
        if ctag.startswith("carFollowing-"):
            model = model or ctag.removeprefix("carFollowing-")
            params.update(_floats(child.attrib))
        elif ctag == "param" and child.get("key"):
            params.update(_floats({child.get("key", ""): child.get("value", "")}))
    params.update(_floats(elem.attrib))
    try:
        min_gap_m = float(elem.get("minGap", repr(default_gap)))
    except ValueError:
        min_gap_m = math.nan
    if not (min_gap_m >= 0 and math.isfinite(min_gap_m)):
        return f"{file}: vType '{tid}' has minGap '{elem.get('minGap')}'; accepted: >= 0 in m"
    return VType(tid, length_m, min_gap_m, model or "Krauss", params)


def _floats(attrib: dict[str, str]) -> dict[str, float]:
    """The numeric attributes (speedFactor="norm(1,0.1)" and the like are skipped)."""
    out: dict[str, float] = {}
    for key, value in attrib.items():
        if key in _NOT_PARAMS:
            continue
        try:
            out[key] = float(value)
        except ValueError:
            continue
    return out


def check_demand(inputs: SumoInputs, net: sumolib.net.Net) -> dict[str, VType]:
    """Check that the demand fits the network; return the vTypes vehicles can have.

    Every route, vehicle, flow and trip in the route and additional files may only use edges
    of the network (``edges=``, ``from``/``to``/``via``, routes nested in vehicles or route
    distributions), and there must be at least one vehicle, trip or flow. A vType without
    ``length`` or ``minGap`` has SUMO's default for its ``vClass`` (``VCLASS_DEFAULTS``: 5 m
    and 2.5 m for a passenger car), as SUMO drives it; SUMO's implicit ``DEFAULT_VEHTYPE``
    (vehicles without ``type=``) is a passenger car with Krauss. A vTypeDistribution stands
    for its members. Returns the used vTypes by id (members, not distributions, since SUMO
    reports a vehicle's member type).
    """
    net_name = Path(inputs.net_file).name
    files = [*inputs.route_files, *inputs.additional_files]
    vtypes: dict[str, tuple[Path, ET.Element]] = {}
    dists: dict[str, list[str]] = {}
    routes: set[str] = set()
    users: list[tuple[Path, str, str, str]] = []  # file, element kind, element id, vType id

    def check_edges(file: Path, kind: str, eid: str, edges: Sequence[str]) -> None:
        for edge in edges:
            if not net.hasEdge(edge):
                raise UserError(
                    f"{file}: {kind} '{eid}' uses edge '{edge}' which is not in {net_name}"
                )

    def check_route(file: Path, elem: ET.Element, owner_kind: str, owner_id: str) -> None:
        """A route element; a nested one without id is named by its vehicle or distribution."""
        rid = elem.get("id", "")
        kind, name = ("route", rid) if rid else (f"route of {owner_kind}", owner_id)
        check_edges(file, kind, name, elem.get("edges", "").split())
        if rid:
            routes.add(rid)

    for file, elem in top_elements(files):
        tag = local_tag(elem.tag)
        eid = elem.get("id", "")
        if tag == "vType":
            vtypes[eid] = (file, elem)
        elif tag == "vTypeDistribution":
            members = elem.get("vTypes", "").split()
            for child in elem:
                if local_tag(child.tag) == "vType":
                    vtypes[child.get("id", "")] = (file, child)
                    members.append(child.get("id", ""))
            dists[eid] = members
        elif tag == "route":
            check_route(file, elem, "route", eid)
        elif tag == "routeDistribution":
            routes.add(eid)
            for child in elem:
                if local_tag(child.tag) == "route":
                    check_route(file, child, "routeDistribution", eid)
        elif tag in _VEHICLE_TAGS:
            kind = tag
            ends = [elem.get(a) for a in ("from", "to")] + elem.get("via", "").split()
            check_edges(file, kind, eid, [e for e in ends if e])
            for child in elem:
                ctag = local_tag(child.tag)
                if ctag == "route":
                    check_route(file, child, kind, eid)
                elif ctag == "routeDistribution":
                    for sub in child:
                        if local_tag(sub.tag) == "route":
                            check_route(file, sub, kind, eid)
            users.append((file, kind, eid, elem.get("type", DEFAULT_VEHTYPE)))

    # Route references are resolved after the loop: SUMO allows them in any loaded file.
    for file, elem in top_elements(files):
        tag = local_tag(elem.tag)
        if tag in _VEHICLE_TAGS and elem.get("route") and elem.get("route") not in routes:
            raise UserError(
                f"{file}: {tag} '{elem.get('id', '')}' uses route '{elem.get('route')}' "
                "which is defined in none of the route or additional files"
            )

    if not users:
        where = ", ".join(str(f) for f in files) or f"{inputs.sumocfg or inputs.net_file}"
        raise UserError(
            f"{where}: the demand has no vehicle, trip or flow, so SUMO would drive nothing; "
            "accepted: at least one <vehicle>, <trip> or <flow> in the route or additional files"
        )
    used: dict[str, VType] = {}
    for file, kind, eid, type_id in users:
        members = dists.get(type_id, [type_id])
        for member in members:
            if member in used:
                continue
            if member in vtypes:
                vfile, velem = vtypes[member]
                parsed = _vtype_from_xml(velem, vfile)
                if isinstance(parsed, str):
                    raise UserError(parsed)
                used[member] = parsed
            elif member == DEFAULT_VEHTYPE:
                used[member] = VType(DEFAULT_VEHTYPE, *VCLASS_DEFAULT, "Krauss", {})
            else:
                raise UserError(
                    f"{file}: {kind} '{eid}' uses vType '{member}' which is defined in none "
                    "of the route or additional files"
                )
    return used


def check_vehicle_ids(inputs: SumoInputs, ids: Sequence[str], where: str) -> None:
    """Every id of ``ids`` names a vehicle the demand can insert: a ``<vehicle>`` or ``<trip>``
    id, or ``<flow id>.<n>`` (SUMO names a flow's vehicles so). ``where`` names the key."""
    files = [*inputs.route_files, *inputs.additional_files]
    single: set[str] = set()
    flows: set[str] = set()
    for _file, elem in top_elements(files):
        tag = local_tag(elem.tag)
        if tag in ("vehicle", "trip"):
            single.add(elem.get("id", ""))
        elif tag == "flow":
            flows.add(elem.get("id", ""))
    for vid in ids:
        flow, dot, n = vid.rpartition(".")
        if vid in single or (dot and n.isdigit() and flow in flows):
            continue
        known = sorted(single)[:3] + [f"{f}.<n>" for f in sorted(flows)[:3]]
        raise UserError(
            f"{where} names '{vid}', which no vehicle of the demand has; accepted: the id of a "
            f"<vehicle> or <trip>, or <flow id>.<n> ({', '.join(known) or 'none'}"
            f"{', ...' if len(single) + len(flows) > len(known) else ''})"
        )

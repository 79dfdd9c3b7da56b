"""Reading and validating a user's own SUMO files (network, demand, detectors).

A user's network arrives as SUMO files written for another purpose. Everything this package
later relies on (edges of the section, vehicle lengths for spacing, detector lanes) is checked
here once, before any simulation starts, and every problem becomes a one-line ``UserError``
that names the file, the element and the value. Only sumolib and ``xml.etree`` are used:
``macromicro_sumo.sumo`` stays the one libsumo importer.
"""

from __future__ import annotations

import gzip
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import quoteattr

import sumolib

from macromicro_sumo.errors import UserError
from macromicro_sumo.files import refuse_comma

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

DETECTOR_PERIOD_DEFAULT_S = 900.0
"""SUMO's default aggregation period of E1/E2 detectors when neither period nor freq is given."""

_E1_TAGS = ("inductionLoop", "e1Detector")
_E2_TAGS = ("laneAreaDetector", "e2Detector")
_VEHICLE_TAGS = ("vehicle", "flow", "trip")
_NOT_PARAMS = {"id", "length", "minGap", "carFollowModel", "vClass", "color", "guiShape"}


# ---------------------------------------------------------------- input files


@dataclass(frozen=True)
class SumoInputs:
    """The SUMO files of one scenario, all existing, paths as SUMO should open them."""

    net_file: Path
    route_files: tuple[Path, ...]
    additional_files: tuple[Path, ...]
    sumocfg: Path | None


def _open_xml(path: Path):
    """A binary stream of ``path``, gunzipped if it is gzip (SUMO reads both)."""
    with open(path, "rb") as fh:
        magic = fh.read(2)
    return gzip.open(path, "rb") if magic == b"\x1f\x8b" else open(path, "rb")


def _root_tag(path: Path) -> str:
    """The root element's tag of an XML file, or UserError if it is not XML at all."""
    try:
        with _open_xml(path) as fh:
            for _event, elem in ET.iterparse(fh, events=("start",)):
                return _local(elem.tag)
    except (ET.ParseError, OSError, EOFError) as exc:
        raise UserError(f"{path}: not an XML file ({exc})") from None
    raise UserError(f"{path}: empty XML file")


def _local(tag: str) -> str:
    """Tag without an XML namespace (SUMO files are written without one, but may carry it)."""
    return tag.rsplit("}", 1)[-1]


def _parse(path: Path) -> ET.Element:
    """The whole tree of a (possibly gzipped) XML file; UserError if it is not XML."""
    try:
        with _open_xml(path) as fh:
            return ET.parse(fh).getroot()
    except (ET.ParseError, OSError, EOFError) as exc:
        raise UserError(f"{path}: not an XML file ({exc})") from None


def _split_files(value: str) -> list[str]:
    """SUMO's list option syntax: comma and/or whitespace separated file names."""
    return [p for p in re.split(r"[,\s]+", value.strip()) if p]


def _must_exist(path: Path, what: str, where: str) -> Path:
    if not path.is_file():
        raise UserError(f"{where}: {what} {path} does not exist")
    return path


def resolve_inputs(
    sumocfg: Path | None,
    net_file: Path | None,
    route_files: Sequence[Path],
    additional_files: Sequence[Path],
    where: str,
) -> SumoInputs:
    """Collect the scenario's SUMO files from a .sumocfg and/or explicit paths.

    The .sumocfg's ``net-file``, ``route-files`` and ``additional-files`` are read relative to
    the .sumocfg's folder, as SUMO does. An explicit ``net_file`` replaces the .sumocfg's;
    explicit route and additional files are added after the .sumocfg's. ``where`` names the
    place the paths came from (e.g. ``"scenarios/x.toml [network]"``) for error messages.
    """
    cfg_net: Path | None = None
    cfg_routes: list[Path] = []
    cfg_adds: list[Path] = []
    if sumocfg is not None:
        sumocfg = _must_exist(Path(sumocfg), "sumocfg", where)
        root = _parse(sumocfg)
        if _local(root.tag) not in ("sumoConfiguration", "configuration"):
            raise UserError(
                f"{sumocfg}: not a SUMO configuration (root element <{_local(root.tag)}>, "
                "expected <sumoConfiguration>)"
            )
        base = sumocfg.parent
        for elem in root.iter():
            tag, value = _local(elem.tag), elem.get("value", "")
            if tag == "net-file":
                cfg_net = base / value.strip()
            elif tag == "route-files":
                cfg_routes += [base / p for p in _split_files(value)]
            elif tag == "additional-files":
                cfg_adds += [base / p for p in _split_files(value)]
        for p in [cfg_net, *cfg_routes, *cfg_adds]:
            if p is not None:
                _must_exist(p, "file named in the sumocfg", str(sumocfg))
    net = Path(net_file) if net_file is not None else cfg_net
    if net is None:
        raise UserError(f"{where}: no network: give net_file or a sumocfg with <net-file>")
    _must_exist(net, "net_file", where)
    routes = [*cfg_routes, *(_must_exist(Path(p), "route file", where) for p in route_files)]
    adds = [*cfg_adds, *(_must_exist(Path(p), "additional file", where) for p in additional_files)]
    for path in (net, *routes, *adds):
        refuse_comma(path, where)
    return SumoInputs(net, tuple(routes), tuple(adds), sumocfg)


def read_net(path: Path) -> sumolib.net.Net:
    """The network of ``path`` (plain or gzipped), checked to be SUMO network XML first.

    sumolib reads any XML without complaint and returns an empty network; checking the root
    element turns a wrong file into a message instead of "edge not found" much later.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: network file does not exist")
    root = _root_tag(path)
    if root != "net":
        raise UserError(f"{path}: not a SUMO network (root element <{root}>, expected <net>)")
    return sumolib.net.readNet(str(path), withInternal=False)


# ---------------------------------------------------------------- demand


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
        ctag = _local(child.tag)
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


def _demand_elements(files: Sequence[Path]) -> Iterator[tuple[Path, ET.Element]]:
    """Every top-level element of the demand and additional files, with its file."""
    for file in files:
        for elem in _parse(file):
            yield file, elem


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

    for file, elem in _demand_elements(files):
        tag = _local(elem.tag)
        eid = elem.get("id", "")
        if tag == "vType":
            vtypes[eid] = (file, elem)
        elif tag == "vTypeDistribution":
            members = elem.get("vTypes", "").split()
            for child in elem:
                if _local(child.tag) == "vType":
                    vtypes[child.get("id", "")] = (file, child)
                    members.append(child.get("id", ""))
            dists[eid] = members
        elif tag == "route":
            check_route(file, elem, "route", eid)
        elif tag == "routeDistribution":
            routes.add(eid)
            for child in elem:
                if _local(child.tag) == "route":
                    check_route(file, child, "routeDistribution", eid)
        elif tag in _VEHICLE_TAGS:
            kind = tag
            ends = [elem.get(a) for a in ("from", "to")] + elem.get("via", "").split()
            check_edges(file, kind, eid, [e for e in ends if e])
            for child in elem:
                ctag = _local(child.tag)
                if ctag == "route":
                    check_route(file, child, kind, eid)
                elif ctag == "routeDistribution":
                    for sub in child:
                        if _local(sub.tag) == "route":
                            check_route(file, sub, kind, eid)
            users.append((file, kind, eid, elem.get("type", DEFAULT_VEHTYPE)))

    # Route references are resolved after the loop: SUMO allows them in any loaded file.
    for file, elem in _demand_elements(files):
        tag = _local(elem.tag)
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


def check_ring_routes(path: Path, edge_ids: Sequence[str], net_file: Path) -> None:
    """The ring's routes file (``network.routes_file``), checked before SUMO starts.

    Vehicles are inserted on route ``r_<edge>`` of the edge they start on and kept going
    round by a rerouter on every edge (``scripts/build_ring_net.py`` writes both). A missing
    route made SUMO fail at the first insertion, a missing rerouter let vehicles leave the
    ring at the end of their route.
    """
    path = Path(path)
    root = _parse(path)
    tag = _local(root.tag)
    if tag not in ("additional", "routes"):
        raise UserError(
            f"{path}: not a SUMO routes file (root element <{tag}>, expected <additional> or "
            "<routes>)"
        )
    routes: dict[str, list[str]] = {}
    rerouted: set[str] = set()
    for elem in root:
        kind = _local(elem.tag)
        if kind == "route":
            routes[elem.get("id", "")] = elem.get("edges", "").split()
        elif kind == "rerouter":
            rerouted.update(elem.get("edges", "").split())
    ring = set(edge_ids)
    for edge in edge_ids:
        rid = f"r_{edge}"
        if rid not in routes:
            raise UserError(
                f"{path}: no route '{rid}'; the ring of {Path(net_file).name} needs a route "
                f"r_<edge> starting on each of its edges ({', '.join(edge_ids)}); "
                "scripts/build_ring_net.py writes them"
            )
        off = [e for e in routes[rid] if e not in ring]
        if off:
            raise UserError(
                f"{path}: route '{rid}' uses edge '{off[0]}' which is not on the ring of "
                f"{Path(net_file).name}"
            )
        if not routes[rid] or routes[rid][0] != edge:
            raise UserError(f"{path}: route '{rid}' does not start on edge '{edge}'")
        if edge not in rerouted:
            raise UserError(
                f"{path}: no rerouter on ring edge '{edge}'; vehicles would leave the ring at "
                "the end of their route (scripts/build_ring_net.py writes routes and rerouters)"
            )


def check_vehicle_ids(inputs: SumoInputs, ids: Sequence[str], where: str) -> None:
    """Every id of ``ids`` names a vehicle the demand can insert: a ``<vehicle>`` or ``<trip>``
    id, or ``<flow id>.<n>`` (SUMO names a flow's vehicles so). ``where`` names the key."""
    files = [*inputs.route_files, *inputs.additional_files]
    single: set[str] = set()
    flows: set[str] = set()
    for _file, elem in _demand_elements(files):
        tag = _local(elem.tag)
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


# ---------------------------------------------------------------- detectors


@dataclass(frozen=True)
class DetectorSpec:
    """One E1 or E2 detector of the user's additional files.

    ``pos_m`` is measured from the start of ``lane_id`` (SUMO's negative positions, counted
    from the lane's end, are converted). A multi-lane E2 (``lanes=``) is kept as ONE detector,
    since SUMO reports it under one id: ``lane_id``/``pos_m`` are its first lane and start,
    ``length_m`` is its whole length over all lanes and ``lane_ids`` lists the lanes.
    ``file`` is SUMO's output file, resolved against the additional file's folder as SUMO does.
    """

    id: str
    kind: str
    lane_id: str
    pos_m: float
    length_m: float
    period_s: float
    file: str
    lane_ids: tuple[str, ...] = ()


def _lane_length(net: sumolib.net.Net, lane_id: str) -> float | None:
    """Length of a lane of the net, or None if the net has no such lane."""
    edge_id, _, index = lane_id.rpartition("_")
    if not edge_id or not index.isdigit() or not net.hasEdge(edge_id):
        return None
    edge = net.getEdge(edge_id)
    if int(index) >= edge.getLaneNumber():
        return None
    return edge.getLane(int(index)).getLength()


def _number(file: Path, did: str, elem: ET.Element, names: Sequence[str], default: float | None):
    """The first attribute of ``names`` as a float; UserError if it is not a number."""
    for name in names:
        raw = elem.get(name)
        if raw is not None:
            try:
                return float(raw)
            except ValueError:
                raise UserError(
                    f"{file}: detector '{did}' has {name}='{raw}'; accepted: a number"
                ) from None
    return default


def user_detectors(inputs: SumoInputs, net: sumolib.net.Net) -> list[DetectorSpec]:
    """The E1 and E2 detectors in the additional files, checked against the network.

    A detector whose lane is not in the network is almost always a detector file written for
    another network (or another version of it); that is an error, not a skip.
    """
    net_name = Path(inputs.net_file).name
    specs: list[DetectorSpec] = []
    for file, elem in _demand_elements(inputs.additional_files):
        tag = _local(elem.tag)
        if tag not in _E1_TAGS + _E2_TAGS:
            continue
        did = elem.get("id", "")
        lanes = elem.get("lanes", "").split() or [elem.get("lane", "")]
        lengths = []
        for lane in lanes:
            lane_len = _lane_length(net, lane)
            if lane_len is None:
                raise UserError(
                    f"{file}: detector '{did}' is on lane '{lane}' which is not in {net_name} "
                    "(a detector file for another network?)"
                )
            lengths.append(lane_len)
        period = _number(file, did, elem, ("period", "freq"), DETECTOR_PERIOD_DEFAULT_S)
        out = elem.get("file", "")
        out_file = str((file.parent / out).resolve()) if out else ""
        if tag in _E1_TAGS:
            pos = _number(file, did, elem, ("pos",), 0.0)
            pos = pos + lengths[0] if pos < 0 else pos
            specs.append(DetectorSpec(did, "e1", lanes[0], pos, 0.0, period, out_file, (lanes[0],)))
            continue
        pos = _number(file, did, elem, ("pos",), None)
        end = _number(file, did, elem, ("endPos",), None)
        length = _number(file, did, elem, ("length",), None)
        if pos is not None and pos < 0:
            pos += lengths[0]
        if end is not None and end < 0:
            end += lengths[-1]
        if len(lanes) > 1:
            pos = 0.0 if pos is None else pos
            end = lengths[-1] if end is None else end
            length = (lengths[0] - pos) + sum(lengths[1:-1]) + end
        elif length is None:
            pos = 0.0 if pos is None else pos
            length = (lengths[0] if end is None else end) - pos
        elif pos is None:
            pos = (lengths[0] if end is None else end) - length
        specs.append(DetectorSpec(did, "e2", lanes[0], pos, length, period, out_file, tuple(lanes)))
    return specs


def auto_detectors_xml(
    lane_ids_positions: list[tuple[str, float]], period_s: float, output_file: str
) -> str:
    """An additional file with one E1 inductionLoop per (lane, position), as a string.

    Ids are ``auto_<lane>_<k>``, k counting the loops of that lane in the given order, so they
    never collide with the user's own detector ids (which ``user_detectors`` reports).
    """
    counts: dict[str, int] = {}
    lines = ["<additional>"]
    for lane, pos in lane_ids_positions:
        k = counts.get(lane, 0)
        counts[lane] = k + 1
        lines.append(
            f"    <inductionLoop id={quoteattr(f'auto_{lane}_{k}')} lane={quoteattr(lane)} "
            f'pos="{pos:.3f}" period="{period_s:g}" file={quoteattr(output_file)}/>'
        )
    lines.append("</additional>")
    return "\n".join(lines) + "\n"

"""Reading and validating a user's own SUMO files: which files (a .sumocfg and/or explicit
paths), their XML, the network, and the user's E1/E2 detectors.

A user's network arrives as SUMO files written for another purpose. Everything this package
later relies on (edges of the section, vehicle lengths for spacing, detector lanes) is checked
once, before any simulation starts, and every problem becomes a one-line ``UserError`` that
names the file, the element and the value; the demand's checks are ``sumo/demand.py``'s. Only
sumolib and ``xml.etree`` are used: ``macromicro_sumo.sumo.simulation`` stays the one libsumo
importer.
"""

from __future__ import annotations

import gzip
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import sumolib

from macromicro_sumo.errors import UserError
from macromicro_sumo.files import refuse_comma
from macromicro_sumo.scenario.section import SectionScenario

DETECTOR_PERIOD_DEFAULT_S = 900.0
"""SUMO's default aggregation period of E1/E2 detectors when neither period nor freq is given."""

_E1_TAGS = ("inductionLoop", "e1Detector")
_E2_TAGS = ("laneAreaDetector", "e2Detector")


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
                return local_tag(elem.tag)
    except (ET.ParseError, OSError, EOFError) as exc:
        raise UserError(f"{path}: not an XML file ({exc})") from None
    raise UserError(f"{path}: empty XML file")


def local_tag(tag: str) -> str:
    """Tag without an XML namespace (SUMO files are written without one, but may carry it)."""
    return tag.rsplit("}", 1)[-1]


def parse_xml(path: Path) -> ET.Element:
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
        root = parse_xml(sumocfg)
        if local_tag(root.tag) not in ("sumoConfiguration", "configuration"):
            raise UserError(
                f"{sumocfg}: not a SUMO configuration (root element <{local_tag(root.tag)}>, "
                "expected <sumoConfiguration>)"
            )
        base = sumocfg.parent
        for elem in root.iter():
            tag, value = local_tag(elem.tag), elem.get("value", "")
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


def read_net(path: Path, with_internal: bool = False) -> sumolib.net.Net:
    """The network of ``path`` (plain or gzipped), checked to be SUMO network XML first;
    ``with_internal`` keeps the junctions' internal lanes (a section's arc runs over them).

    sumolib reads any XML without complaint and returns an empty network; checking the root
    element turns a wrong file into a message instead of "edge not found" much later.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: network file does not exist")
    root = _root_tag(path)
    if root != "net":
        raise UserError(f"{path}: not a SUMO network (root element <{root}>, expected <net>)")
    try:
        return sumolib.net.readNet(str(path), withInternal=with_internal)
    except Exception as exc:  # sumolib raises bare parser errors
        raise UserError(f"{path}: not a readable SUMO network ({type(exc).__name__})") from None


def top_elements(files: Sequence[Path]) -> Iterator[tuple[Path, ET.Element]]:
    """Every top-level element of the demand and additional files, with its file."""
    for file in files:
        for elem in parse_xml(file):
            yield file, elem


# SUMO's traffic-light program elements of an additional file (programs, and the WAUTs that
# switch between them).
SIGNAL_PROGRAM_TAGS = ("tlLogic", "WAUT", "wautJunction")


def signal_programs(inputs: SumoInputs, dst: Path) -> tuple[Path, ...]:
    """The traffic-light programs of the user's additional files alone, written to ``dst``
    (one file; none where they define no program): for a run that defines its own vTypes,
    routes and detectors (a Stage II env) and must still show the signals the truth's
    run showed, whose recorded program may be one of these (``signals.csv``)."""
    found = [e for _, e in top_elements(inputs.additional_files)]
    found = [e for e in found if local_tag(e.tag) in SIGNAL_PROGRAM_TAGS]
    if not found:
        return ()
    root = ET.Element("additional")
    root.extend(found)
    ET.ElementTree(root).write(dst)
    return (dst,)


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
    for file, elem in top_elements(inputs.additional_files):
        tag = local_tag(elem.tag)
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


def scenario_inputs(sc: SectionScenario) -> SumoInputs:
    """The user's SUMO files named by a section scenario, resolved and checked to exist."""
    n = sc.network
    return resolve_inputs(
        sc.resolve(n.sumocfg) if n.sumocfg else None,
        sc.resolve(n.net_file) if n.net_file else None,
        [sc.resolve(p) for p in n.route_files],
        [sc.resolve(p) for p in n.additional_files],
        sc.source,
    )


def input_files(sc: SectionScenario) -> list[Path]:
    """Every file besides the scenario file that a scenario reads, once each: its SUMO
    files (the .sumocfg and every file it names, and the explicit ones). What ``--out``
    must not hold and what a batch ships to a Ray node."""
    i = scenario_inputs(sc)
    files = [*([i.sumocfg] if i.sumocfg else []), i.net_file, *i.route_files]
    files += i.additional_files
    return list(dict.fromkeys(Path(f) for f in files))

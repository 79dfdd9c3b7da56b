"""A section's detectors: the user's own E1/E2 on the section, else E1 loops placed every
``auto_spacing_m`` on every lane; our definitions of them (an instantaneous loop beside
every E1 loop, our output files and interval, the user's additional files copied without
their detectors) and the reading of their output after a run.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import pandas as pd
import sumolib

from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import DetectorSpec, SumoInputs, read_net, user_detectors
from macromicro_sumo.truth.stations import STOP_BAR_M, side_junction_arcs

E1_FILE, E2_FILE, INSTANT_FILE = "e1.xml", "e2.xml", "instant.xml"
OCCUPANCY_FILE = "e1_occupancy.xml"
"""The occupancy loops' output (``detectors.auto_occupancy_loop_m``): ids ``o_`` + the
point loop's."""
_DETECTOR_TAGS = {
    "inductionLoop",
    "e1Detector",
    "laneAreaDetector",
    "e2Detector",
    "instantInductionLoop",
}


@dataclass(frozen=True)
class Placed:
    """A detector on the section: its SUMO definition and where it sits on the arc."""

    spec: DetectorSpec
    source: str  # "user" or "auto"
    lane_index: int
    arc_m: float


BOUNDARY_STATION_M = 15.0
"""How far inside the section's open ends and either side of a ramp's node the boundary
stations sit (``detectors.auto_boundary_stations``): past the front of a 12 m truck
inserted at a lane's start, and clear of the junction."""

STOP_NODE_TYPES = (
    "traffic_light",
    "traffic_light_unregulated",
    "traffic_light_right_on_red",
    "allway_stop",
    "priority_stop",
    "right_before_left",
    "left_before_right",
)
"""SUMO node types at which a section's vehicles may queue at the stop line: a boundary
station ``STOP_BAR_M`` before it (``boundary_arcs``)."""


def place_detectors(sc: SectionScenario, inputs: SumoInputs, section: Section) -> list[Placed]:
    """The user's detectors on the section, else loops every ``auto_spacing_m`` per lane,
    none past an open section's ``exit_arc`` (with ``auto_boundary_stations``, and at
    ``boundary_arcs``)."""
    placed: list[Placed] = []
    if sc.detectors.use_user:
        net = read_net(inputs.net_file)
        for spec in user_detectors(inputs, net):
            hit = section.locate(spec.lane_id, spec.pos_m)
            if hit is not None and not spec.lane_id.startswith(":"):
                placed.append(Placed(spec, "user", hit[0], hit[1]))
    if placed:
        return placed
    step = sc.detectors.auto_spacing_m
    if step <= 0:
        raise UserError(
            f"{sc.source}: the section has no detector of the user's files and "
            "detectors.auto_spacing_m = 0 switches placement off; accepted: auto_spacing_m > 0"
        )
    period = sc.detectors.interval_s
    occupancy_loop = sc.detectors.auto_occupancy_loop_m
    arcs = np.arange(step / 2, section.length_m, step)
    if not section.closed:
        arcs = np.unique(np.minimum(arcs, exit_arc(section)))
    if sc.detectors.auto_boundary_stations:
        arcs = merge_arcs(arcs, boundary_arcs(section, read_net(inputs.net_file)))
    for arc in arcs:
        e = int(section.edge_index(np.array([arc]))[0])
        pos = float(arc - section.offsets_m[e])
        if pos > section.lengths_m[e] - 0.5 + 1e-6:  # a stop bar's 0.5 m, to rounding
            continue  # in a junction: skip this station
        for lane_id in section.edge_lane_ids[e]:
            idx = section.lanes[lane_id][1]
            # An E1's length_m: its occupancy loop's (dual loop, ``detectors_xml``), 0: none.
            spec = DetectorSpec(
                f"auto_{lane_id}_{arc:.0f}", "e1", lane_id, pos, occupancy_loop, period, ""
            )
            placed.append(Placed(spec, "auto", idx, float(arc)))
    if not placed:
        raise UserError(
            f"{sc.source}: detectors.auto_spacing_m = {step:g} places no loop on a "
            f"{section.length_m:.0f} m section; accepted: < {section.length_m:.0f}"
        )
    return placed


def exit_arc(section: Section) -> float:
    """The last arc of an open section at which a loop sees every vehicle leave:
    ``BOUNDARY_STATION_M`` before its end (at most half the last edge in). A vehicle whose
    route ends there arrives with its front at the lane's end (SUMO's default arrivalPos),
    and one that arrives with its back still on an E1 loop leaves it without being counted
    in ``nVehContrib`` (its instantaneous loop does report the 'enter'). On arterial 600
    (453 m, a loop every 100 m) the loop at 450 m counted 197 of its 283 passages in run 0:
    86 arrived on it. A grid loop past this arc moves to it."""
    d = min(BOUNDARY_STATION_M, 0.5 * float(section.lengths_m[-1]))
    return float(section.offsets_m[-1] + section.lengths_m[-1] - d)


def boundary_arcs(section: Section, net: sumolib.net.Net) -> np.ndarray:
    """Arcs of the stations that bound every counted stretch: ``BOUNDARY_STATION_M`` inside
    each end of an open section, and as far before and after each node where a ramp joins
    or leaves (``side_junction_arcs``), on the edges either side of it (at most half an
    edge in), and ``STOP_BAR_M`` before the end of every section edge that ends at a
    signal or a stop sign (``STOP_NODE_TYPES``). With full stations there, every vehicle
    that enters or leaves the section passes one: the end pieces and the stretches around
    a ramp shrink to a few metres, a queue at a stop line stands on a counted stretch, and
    every other stretch is counted by its stations alone (docs/sections.md, "Hidden
    count")."""
    n = len(section.edge_ids)

    def inside(e: int, from_end: bool) -> float:
        d = min(BOUNDARY_STATION_M, 0.5 * float(section.lengths_m[e]))
        return float(section.offsets_m[e] + (section.lengths_m[e] - d if from_end else d))

    arcs = []
    if not section.closed:
        arcs += [inside(0, False), inside(n - 1, True)]
    for node_arc in side_junction_arcs(net, section):
        e = int(np.argmin(np.abs(section.offsets_m - node_arc)))
        arcs += [inside((e - 1) % n, True), inside(e, False)]
    for e, eid in enumerate(section.edge_ids):
        if net.getEdge(eid).getToNode().getType() in STOP_NODE_TYPES:
            end = float(section.offsets_m[e] + section.lengths_m[e])
            arcs.append(max(end - STOP_BAR_M, float(section.offsets_m[e])))
    return np.array(sorted(set(arcs)))


def merge_arcs(arcs_m: np.ndarray, extra_m: np.ndarray, apart_m: float = 1.0) -> np.ndarray:
    """``arcs_m`` with ``extra_m`` added, an extra arc within ``apart_m`` of one already
    there left out (two stations a metre apart count the same vehicles)."""
    a = np.asarray(arcs_m, dtype=float)
    keep = [x for x in extra_m if a.size == 0 or np.abs(a - x).min() >= apart_m]
    return np.sort(np.concatenate([a, keep]))


def detectors_xml(placed: list[Placed], interval_s: float) -> str:
    """Our definitions of the detectors (E1 + an instantaneous loop beside it, or E2).

    A placed E1 with a ``length_m`` (``detectors.auto_occupancy_loop_m``) is a dual loop: the
    point loop gives the counts and speeds, a second E1 that long, ending at it, the interval
    occupancy only (``read_detectors``). Not one E1 with a length: SUMO's counts a vehicle
    when it leaves the loop and drops one that changes lane over it (drawn seed 500, 2 runs:
    9537 -> 9396 counted, the interval counts' K 0.96 -> 7.58 per lane; docs/sections-log.md,
    stop 42 hL), where a field loop counts on entry."""
    rows = ["<additional>"]
    for p in placed:
        s = p.spec
        did, lane = quoteattr(s.id), quoteattr(s.lane_id)
        if s.kind == "e1":
            rows.append(
                f'    <inductionLoop id={did} lane={lane} pos="{s.pos_m:.3f}" '
                f'period="{interval_s:g}" file="{E1_FILE}"/>'
            )
            if p.source == "auto" and s.length_m > 0:
                # Ends at the point loop (a loop past a lane's end is refused by SUMO; stop
                # bars sit 0.5 m before it), from the lane's start where that is nearer.
                rows.append(
                    f"    <inductionLoop id={quoteattr('o_' + s.id)} lane={lane} "
                    f'pos="{max(s.pos_m - s.length_m, 0.0):.3f}" length="{s.length_m:g}" '
                    f'period="{interval_s:g}" file="{OCCUPANCY_FILE}"/>'
                )
            rows.append(
                f"    <instantInductionLoop id={quoteattr('i_' + s.id)} lane={lane} "
                f'pos="{s.pos_m:.3f}" file="{INSTANT_FILE}"/>'
            )
        elif len(s.lane_ids) > 1:
            lanes = quoteattr(" ".join(s.lane_ids))
            rows.append(
                f'    <laneAreaDetector id={did} lanes={lanes} pos="{s.pos_m:.3f}" '
                f'length="{s.length_m:.3f}" period="{interval_s:g}" file="{E2_FILE}"/>'
            )
        else:
            # One lane: lane= with length=. In the lanes= form SUMO ignores length and runs
            # the area to the lane's end (a 150 m area read as 476 m: densities 3.2x off).
            rows.append(
                f'    <laneAreaDetector id={did} lane={lane} pos="{s.pos_m:.3f}" '
                f'length="{s.length_m:.3f}" period="{interval_s:g}" file="{E2_FILE}"/>'
            )
    rows.append("</additional>")
    return "\n".join(rows) + "\n"


def without_detectors(src: Path, dst: Path) -> Path:
    """A copy of a user's additional file minus its detectors (we define our own)."""
    tree = ET.parse(src)
    root = tree.getroot()
    for parent in list(root.iter()):
        for child in list(parent):
            if child.tag.split("}")[-1] in _DETECTOR_TAGS:
                parent.remove(child)
    tree.write(dst)
    return dst


def read_detectors(
    run_dir: Path, run: int, placed: list[Placed]
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per-interval table, per-vehicle passages) of one run's detector output."""
    where = {p.spec.id: p for p in placed}

    def row(r: dict[str, str], kind: str) -> dict[str, object]:
        p = where[r["id"]]
        at = {"lane_index": p.lane_index, "arc_m": p.arc_m}
        return {"run": run, "detector_id": r["id"], "kind": kind, "source": p.source, **at} | {
            "begin_s": float(r["begin"]),
            "end_s": float(r["end"]),
        }

    # The occupancy loops' (dual loops): their occupancy and length replace the point's.
    occupancy = {
        (r["id"].removeprefix("o_"), r["begin"]): float(r["occupancy"])
        for r in records(run_dir / OCCUPANCY_FILE, "interval", required=False)
    }
    rows = []
    for r in records(run_dir / E1_FILE, "interval", required=False):
        flow, speed = float(r["flow"]), speed_or_nan(r.get("harmonicMeanSpeed"))
        occ = occupancy.get((r["id"], r["begin"]))
        rows.append(
            row(r, "e1")
            | {
                "n_veh": int(r["nVehContrib"]),
                "flow_vph": flow,
                "speed_mps": speed,
                "occupancy_pct": float(r["occupancy"]) if occ is None else occ,
                # Fundamental relation k = q / v (harmonic mean: the space-mean speed).
                "density_vpkm": flow / speed / 3.6 if speed > 0 else 0.0,
                # The loop whose occupancy this is: a point (0) or the occupancy loop.
                "length_m": 0.0 if occ is None else where[r["id"]].spec.length_m,
            }
        )
    for r in records(run_dir / E2_FILE, "interval", required=False):
        length = where[r["id"]].spec.length_m
        rows.append(
            row(r, "e2")
            | {
                "n_veh": int(r["nVehSeen"]),
                "flow_vph": np.nan,
                "speed_mps": speed_or_nan(r.get("meanSpeed")),
                "occupancy_pct": float(r["meanOccupancy"]),
                "density_vpkm": e2_vehicles(r) / length * 1000.0,
                "length_m": length,
                "sampled_seconds_s": float(r["sampledSeconds"]),
            }
        )
    det = pd.DataFrame(rows)
    passages = read_passages(run_dir / INSTANT_FILE, run, required=False)
    return det, passages


def e2_vehicles(r: dict[str, str]) -> float:
    """Mean vehicles on a lane-area (E2) detector's length in one interval of its output,
    each counted by the part of it on the detector.

    SUMO counts a vehicle on every detector it overlaps: ``meanVehicleNumber`` and
    ``sampledSeconds`` count one across an edge boundary on both detectors (a vehicle is
    on a detector of length l while its front is on l + its own length L: at density k,
    k (l + L) of them), ``meanVehicleNumber`` also the step in which one leaves. The mean
    occupancy (the share of l under vehicles, k L) is what the overlap adds, so the
    vehicle-seconds per second less it is k l, with no vehicle length needed. On
    ring_sugiyama (22 vehicles, four edge-long E2, 40 runs x 3 intervals): the four
    ``meanVehicleNumber`` summed to 24.47 (24.22-24.74), this to 21.92 (21.75-22.17).
    """
    duration = float(r["end"]) - float(r["begin"])
    if duration <= 0:
        return 0.0
    sampled = float(r["sampledSeconds"]) / duration
    return max(0.0, sampled - float(r["meanOccupancy"]) / 100.0)


def records(path: Path, tag: str, required: bool = True) -> list[dict[str, str]]:
    """Attributes of every ``tag`` element of a SUMO output file (none if it is missing and
    not ``required``: SUMO writes no file for a detector kind that is not defined)."""
    if not path.is_file():
        if not required:
            return []
        raise UserError(f"{path}: detector output missing")
    try:
        return [el.attrib for el in ET.parse(path).getroot().iter(tag)]
    except ET.ParseError as exc:
        raise UserError(f"{path}: detector output is not valid XML ({exc})") from None


def read_passages(path: Path, run: int, required: bool = True) -> pd.DataFrame:
    """Per-vehicle passages ('enter') of the instantaneous loops in ``path``."""
    return pd.DataFrame(
        [
            {
                "run": run,
                "detector_id": r["id"],
                "time_s": float(r["time"]),
                "vehicle_id": r["vehID"],
                "speed_mps": float(r["speed"]),
                "length_m": float(r["length"]),
            }
            for r in records(path, "instantOut", required)
            if r.get("state") == "enter"
        ],
        columns=["run", "detector_id", "time_s", "vehicle_id", "speed_mps", "length_m"],
    )


def speed_or_nan(value: str | None) -> float:
    """SUMO writes -1 for 'no vehicle in this interval'."""
    v = float(value) if value is not None else -1.0
    return np.nan if v < 0 else v

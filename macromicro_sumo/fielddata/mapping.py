"""How a field file's coordinates land on the section: typed settings and the conversion.

A trajectory file measures position along the road from its own origin, in its own units,
numbers lanes its own way (NGSIM and PeMS count from the median, SUMO from the kerb) and
keeps its own clock. ``TrajectoryMapping`` says how to turn that into the section's
``(lane index from the right, arc from the start of the first edge)`` and the truth's
clock; ``StationMapping`` places each station (detector) at an arc and a lane. Both are
the scenario's ``[data]`` conventions (``scenario.data``) plus the run a file's rows get,
so a key is declared once and its errors read as the scenario's.
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.fielddata.schema import unit, where
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.data import (
    ACCEL_UNITS,
    LENGTH_UNITS,
    SPEED_UNITS,
    TIME_UNITS,
    StationConventions,
    StationPlace,
    TrajectoryConventions,
)
from macromicro_sumo.scenario.fields import build_table, spec


@dataclass(frozen=True, kw_only=True)
class TrajectoryMapping(TrajectoryConventions):
    """A trajectory file's coordinates, units and clock -> the section's, as run ``run``."""

    run: int = spec(0, lo=0, hi=1_000_000, doc="run number the file's rows get (a recording)")


@dataclass(frozen=True, kw_only=True)
class StationMapping(StationConventions):
    """A station file's stations, lane numbering and clock -> the section's, as run ``run``."""

    run: int = spec(0, lo=0, hi=1_000_000, doc="run number the file's rows get (a recording)")


def trajectory_mapping(table: dict[str, Any], source: str, **defaults: Any) -> TrajectoryMapping:
    """A ``TrajectoryMapping`` from a scenario table, over a layout's ``defaults``."""
    m = build_table(TrajectoryMapping, {**defaults, **table}, "data.trajectories", source)
    if m.direction not in (1, -1):
        raise UserError(f"{source}: data.trajectories.direction = {m.direction}; accepted: 1, -1")
    return m


def station_mapping(table: dict[str, Any], source: str) -> StationMapping:
    """A ``StationMapping`` from a scenario table with ``stations = [{id, arc_m, lane}, ...]``."""
    table = dict(table)
    places = table.pop("stations", [])
    if not isinstance(places, list):
        raise UserError(f"{source}: data.stations.stations must be a list of tables")
    m = build_table(StationMapping, table, "data.stations", source)
    built = tuple(
        build_table(StationPlace, p, f"data.stations.stations[{i}]", source)
        for i, p in enumerate(places)
    )
    return dataclasses.replace(m, stations=built)


# --------------------------------------------------------------------------- lanes


def lanes_at(section: Section, arc_m: np.ndarray) -> np.ndarray:
    """Lanes of the road at each arc; inside a junction those of the edge it leads to (a
    lane index in a junction is the index of the lane it leads into, as in ``Section``)."""
    arc = np.asarray(arc_m, dtype=float)
    e = section.edge_index(arc)
    s = section.wrap(arc)
    n = len(section.edge_ids)
    in_junction = s > section.offsets_m[e] + section.lengths_m[e]
    nxt = (e + 1) % n if section.closed else np.minimum(e + 1, n - 1)
    return np.where(in_junction, section.n_lanes[nxt], section.n_lanes[e])


def lane_index(
    numbers: np.ndarray, numbering: str, first: int, count: int, lanes_here: np.ndarray
) -> np.ndarray:
    """The section's lane index (0 = rightmost) of the file's lane numbers."""
    k = np.asarray(numbers, dtype=np.int64) - first
    if numbering == "right":
        return k
    width = np.full_like(k, count) if count > 0 else np.asarray(lanes_here, dtype=np.int64)
    return width - 1 - k


def lane_number(
    index: np.ndarray, numbering: str, first: int, count: int, lanes_here: np.ndarray
) -> np.ndarray:
    """Inverse of ``lane_index``: the file's lane number of a section lane index."""
    index = np.asarray(index, dtype=np.int64)
    if numbering == "right":
        return index + first
    width = np.full_like(index, count) if count > 0 else np.asarray(lanes_here, dtype=np.int64)
    return width - 1 - index + first


# --------------------------------------------------------------------------- clocks


def parse_times(values: pd.Series, m: StationMapping, path: Path, column: str) -> np.ndarray:
    """Seconds on the section's clock of date-times (PeMS ``MM/DD/YYYY HH:MM:SS``) or numbers."""
    num = pd.to_numeric(values, errors="coerce")
    if num.notna().all():
        return num.to_numpy(dtype=float) + m.clock_offset_s
    stamps = pd.to_datetime(values, errors="coerce", format="mixed")
    bad = np.flatnonzero(stamps.isna().to_numpy())
    if bad.size:
        i = int(bad[0])
        raise UserError(
            f"{where(path, i, column)}: {values.iloc[i]!r} is neither seconds nor a date-time "
            "(PeMS: MM/DD/YYYY HH:MM:SS)"
        )
    if m.clock_origin:
        try:
            origin = pd.Timestamp(datetime.fromisoformat(m.clock_origin))
        except ValueError:
            raise UserError(
                f"{path}: clock_origin = {m.clock_origin!r} is not an ISO date-time "
                "(YYYY-MM-DDTHH:MM:SS)"
            ) from None
    else:
        origin = stamps.min()  # no origin given: the file's first interval is t = 0
    return (stamps - origin).dt.total_seconds().to_numpy(dtype=float) + m.clock_offset_s


def off_section(section: Section, arc: np.ndarray, lane: np.ndarray) -> np.ndarray:
    """Which (lane, arc) positions are not on the section (outside its arc or its lanes)."""
    inside = np.ones(len(arc), dtype=bool)
    if not section.closed:
        inside = (arc >= 0.0) & (arc <= section.length_m)
    width = lanes_at(section, np.clip(arc, 0.0, section.length_m))
    return ~inside | (lane < 0) | (lane >= width)


def check_on_section(
    section: Section,
    arc: np.ndarray,
    lane: np.ndarray,
    path: Path,
    rows: np.ndarray,
    lines: np.ndarray,
    arc_column: str,
    lane_column: str,
    hint: str,
) -> None:
    """Every (lane, arc) on the section; else one line naming the first row off it
    (its arc column when the arc is off, else its lane column)."""
    off = off_section(section, arc, lane)
    if not off.any():
        return
    i = int(np.flatnonzero(off)[0])
    at = where(path, int(rows[i]), arc_column, int(lines[i]))
    if not section.closed and not 0.0 <= arc[i] <= section.length_m:
        raise UserError(
            f"{at}: section arc {arc[i]:.2f} m is off the section; accepted: "
            f"[0, {section.length_m:.2f}] m; {hint}"
        )
    width = int(lanes_at(section, arc[i : i + 1])[0])
    at = where(path, int(rows[i]), lane_column, int(lines[i]))
    raise UserError(
        f"{at}: lane index {int(lane[i])} (from the right) is not on the section at arc "
        f"{arc[i]:.1f} m; accepted: 0..{width - 1}; {hint}"
    )


def trajectory_units(m: TrajectoryMapping, source: str) -> tuple[float, float, float, float]:
    """SI factors of (length, speed, acceleration, time) of a mapping."""
    return (
        unit(LENGTH_UNITS, m.length_unit, "length_unit", source),
        unit(SPEED_UNITS, m.speed_unit, "speed_unit", source),
        unit(ACCEL_UNITS, m.accel_unit, "accel_unit", source),
        unit(TIME_UNITS, m.time_unit, "time_unit", source),
    )


def _lane_length(section: Section, lane_id: str) -> float:
    """Length of a section lane in its own positions (an internal lane: its junction)."""
    edge, _, _, scale = section.lanes[lane_id]
    along = section.junction_m[edge] if lane_id.startswith(":") else section.lengths_m[edge]
    return float(along / scale)


def e2_length(el: ET.Element, section: Section, additional: Path, k: int, did: str) -> float:
    """Arc length an E2 covers, read as SUMO reads it: with ``lanes`` the area runs from
    ``pos`` on the first lane to ``endPos`` on the last (default: its end) and SUMO ignores
    ``length``; with ``lane``, ``length`` or else ``endPos``. Negative positions count
    from the lane's end."""
    chain = el.get("lanes", "").split()
    first = chain[0] if chain else el.get("lane", "")
    last = chain[-1] if chain else first
    if any(lane not in section.lanes for lane in (first, last)):
        raise UserError(
            f"{additional}: element {k} (E2 {did!r}), attribute 'lanes': {first!r} .. {last!r} "
            f"is not on the section ({', '.join(section.edge_ids)})"
        )

    def at(lane: str, pos: float) -> float:
        pos = pos + _lane_length(section, lane) if pos < 0 else pos
        return section.locate(lane, pos)[1]  # type: ignore[index]  # checked above

    start = at(first, float(el.get("pos", "0")))
    if not chain and el.get("length") is not None:
        return float(el.get("length"))  # type: ignore[arg-type]
    end_pos = el.get("endPos")
    end = at(last, float(end_pos)) if end_pos is not None else at(last, _lane_length(section, last))
    return end - start

"""Station (detector) data from field files, in the ``detectors.csv`` schema.

Layouts: SUMO E1/E2 XML output (placed by the detector definitions of an additional file,
or by a ``StationMapping``), PeMS station files (``station_5min`` columns, 5-minute or
30-second intervals, with or without a header row) and a generic CSV with a column map.
Every reader returns ``Stations``: the frame the pipeline takes unchanged (one row per
station, lane and interval) and each row's data quality (PeMS ``Samples`` and
``% Observed``) for ``cleaning.clean_stations``.

Units in the frame: flow veh/h, speed m/s (space-mean, NaN when no vehicle passed),
occupancy %, density veh/km from the fundamental relation k = q / v (as the ground truth
computes it; 0 without vehicles).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.fielddata.mapping import (
    StationMapping,
    StationPlace,
    check_on_section,
    e2_length,
    lane_index,
    lanes_at,
    parse_times,
)
from macromicro_sumo.fielddata.schema import (
    DET_COLUMNS,
    MAX_SPEED_MPS,
    check_range,
    numbers,
    read_table,
    require_columns,
    unit,
    where,
)
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.data import SPEED_UNITS, STATION_LAYOUT_DEFAULTS, StationColumns

PEMS_FIXED = (
    "Timestamp",
    "Station",
    "District",
    "Freeway",
    "Direction",
    "Lane Type",
    "Station Length",
    "Samples",
    "% Observed",
    "Total Flow",
    "Avg Occupancy",
    "Avg Speed",
)
PEMS_LANE = ("Samples", "Flow", "Avg Occ", "Avg Speed", "Observed")
PEMS_MAPPING = StationMapping(**STATION_LAYOUT_DEFAULTS["pems"])
DEFAULT_MAPPING = StationMapping()


DEFAULT_COLUMNS = StationColumns()


@dataclass(frozen=True)
class Stations:
    """Station data of one file on the section."""

    file: Path
    layout: str
    frame: pd.DataFrame  # detectors.csv schema
    quality: pd.DataFrame  # per frame row: samples, observed_pct (NaN: not in the file)


def _frame(rows: dict[str, np.ndarray], m: StationMapping) -> pd.DataFrame:
    """The detectors.csv frame of per-row arrays (flow veh/h, speed m/s, occupancy %)."""
    speed, flow = rows["speed_mps"], rows["flow_vph"]
    with np.errstate(divide="ignore", invalid="ignore"):
        density = np.where(speed > 0, flow / speed / 3.6, 0.0)
    rows = {**rows, "density_vpkm": rows.get("density_vpkm", density)}
    df = pd.DataFrame({"run": m.run, "source": "field", **rows})
    extra = [c for c in df.columns if c not in DET_COLUMNS]
    return df[list(DET_COLUMNS) + extra]


def _place_all(
    ids: pd.Series, m: StationMapping, section: Section, path: Path, column: str
) -> list[StationPlace]:
    """The mapping's place of every row's station; an unplaced station is one line."""
    places = {s.id: s for s in m.stations}
    out = []
    for i, sid in enumerate(ids.astype(str)):
        p = places.get(sid)
        if p is None:
            known = ", ".join(sorted(places)) or "none"
            raise UserError(
                f"{where(path, i, column)}: station {sid!r} is not placed on the section; "
                f"add it to the station mapping (placed: {known})"
            )
        out.append(p)
    arcs = np.array([p.arc_m for p in places.values()])
    lanes = np.array([max(p.lane, 0) for p in places.values()])
    check_on_section(
        section,
        arcs,
        lanes,
        path,
        np.zeros(len(arcs), dtype=int),
        np.zeros(len(arcs), dtype=int),
        "arc_m",
        "lane",
        "station mapping: " + ", ".join(f"{p.id} at {p.arc_m:g} m" for p in places.values()),
    )
    return out


def _check_speeds(
    speed: np.ndarray, path: Path, column: str, unit_name: str, rows: np.ndarray
) -> None:
    check_range(
        speed,
        0.0,
        MAX_SPEED_MPS,
        path,
        column,
        "speed [m/s]",
        f"is the speed unit {unit_name!r} right (mph read as km/h or m/s is off by 1.6 or 2.2)?",
        rows,
    )


def _check_intervals(
    begin: np.ndarray, end: np.ndarray, path: Path, column: str, rows: np.ndarray
) -> None:
    bad = np.flatnonzero(~(end > begin))
    if bad.size:
        i = int(bad[0])
        raise UserError(
            f"{where(path, int(rows[i]), column)}: empty interval [{begin[i]:g}, {end[i]:g}] s; "
            "accepted: end > begin (set interval_s when the file has no end)"
        )


def infer_interval(begin: np.ndarray, station: np.ndarray, path: Path, m: StationMapping) -> float:
    """The interval length: the mapping's, else the smallest step between a station's rows."""
    if m.interval_s > 0:
        return m.interval_s
    df = pd.DataFrame({"s": station, "b": begin}).drop_duplicates().sort_values(["s", "b"])
    steps = df.groupby("s")["b"].diff().to_numpy()
    steps = steps[np.isfinite(steps) & (steps > 0)]
    if steps.size == 0:
        raise UserError(f"{path}: one interval per station; set the mapping's interval_s [s]")
    return float(steps.min())


# --------------------------------------------------------------------------- PeMS


def read_pems(
    path: Path | str, section: Section, mapping: StationMapping = PEMS_MAPPING
) -> Stations:
    """A PeMS station file (``station_5min`` layout, any interval): ``Timestamp`` (interval
    start, MM/DD/YYYY HH:MM:SS), ``Station``, ``Samples``, ``% Observed``, ``Total Flow``
    (veh per interval), ``Avg Occupancy`` (0-1), ``Avg Speed`` [mph], then per lane N
    ``Lane N Samples / Flow / Avg Occ / Avg Speed / Observed``; lane 1 is the leftmost."""
    path = Path(path)
    df = read_table(path, header=None, dtype=str, skipinitialspace=True)
    if str(df.iloc[0, 0]).strip() == "Timestamp":
        df.columns = [str(c).strip() for c in df.iloc[0]]
        df = df.iloc[1:].reset_index(drop=True)
        first = 2  # a header: data row r stands on line r + 2
    else:
        n_lanes = max((df.shape[1] - len(PEMS_FIXED)) // len(PEMS_LANE), 0)
        names = list(PEMS_FIXED) + [
            f"Lane {k} {c}" for k in range(1, n_lanes + 1) for c in PEMS_LANE
        ]
        df = df.iloc[:, : len(names)]
        df.columns = names[: df.shape[1]]
        first = 1
    require_columns(df, ["Timestamp", "Station", "Total Flow", "Avg Occupancy", "Avg Speed"], path)
    begin = parse_times(df["Timestamp"], mapping, path, "Timestamp")
    interval = infer_interval(begin, df["Station"].to_numpy(), path, mapping)
    places = _place_all(df["Station"], mapping, section, path, "Station")
    lanes = sorted(
        {int(c.split()[1]) for c in df.columns if c.startswith("Lane ") and c.endswith(" Flow")}
    )
    blocks = []
    rows = np.arange(len(df))
    arcs = np.array([p.arc_m for p in places])
    fixed = np.array([p.lane for p in places])
    per_lane = (fixed < 0) & bool(lanes)
    groups = [(f"Lane {k} ", k) for k in lanes] if per_lane.any() else []
    for prefix, k in [("", None), *groups]:
        sel = ~per_lane if k is None else per_lane
        flow_col = "Total Flow" if k is None else f"{prefix}Flow"
        occ_col = "Avg Occupancy" if k is None else f"{prefix}Avg Occ"
        spd_col = "Avg Speed" if k is None else f"{prefix}Avg Speed"
        sub = df[sel]
        if sub.empty:
            continue
        count = numbers(sub, flow_col, path, allow_nan=True)
        occ = numbers(sub, occ_col, path, allow_nan=True)
        speed = numbers(sub, spd_col, path, allow_nan=True) * SPEED_UNITS["mph"]
        _check_speeds(speed, path, spd_col, "mph", rows[sel])
        check_range(
            occ, 0.0, 1.0, path, occ_col, "occupancy (fraction)", "PeMS writes 0-1", rows[sel]
        )
        if k is None:
            lane = np.where(fixed[sel] >= 0, fixed[sel], -1)
            samples = _optional(sub, "Samples", path)
            observed = _optional(sub, "% Observed", path)
        else:
            here = lanes_at(section, arcs[sel])
            lane = lane_index(
                np.full(len(sub), k),
                mapping.lane_numbering,
                mapping.first_lane,
                mapping.lane_count,
                here,
            )
            samples = _optional(sub, f"{prefix}Samples", path)
            obs = _optional(sub, f"{prefix}Observed", path)
            observed = np.where(np.isnan(obs), np.nan, obs * 100.0)
            # A lane without data at all is not a lane of this station.
            has = ~(np.isnan(count) & np.isnan(speed) & np.isnan(occ))
            sub, count, occ, speed, lane, samples, observed, here = (
                x[has] for x in (sub, count, occ, speed, lane, samples, observed, here)
            )
            sel = np.flatnonzero(sel)[has]
            on = (lane >= 0) & (lane < here)
            if not on.all():
                i = int(np.flatnonzero(~on)[0])
                raise UserError(
                    f"{where(path, int(rows[sel[i]]), flow_col)}: lane {k} is not on the section at "
                    f"arc {arcs[sel[i]]:.1f} m ({int(here[i])} lanes there; PeMS lane 1 is the "
                    "leftmost); check the mapping's lane_count and lane_numbering"
                )
        blocks.append(
            (
                pd.DataFrame(
                    {
                        "detector_id": df["Station"].to_numpy()[sel].astype(str),
                        "kind": "e1",
                        "lane_index": lane.astype(np.int64),
                        "arc_m": arcs[sel],
                        "begin_s": begin[sel],
                        "end_s": begin[sel] + interval,
                        "n_veh": count,
                        "flow_vph": count * 3600.0 / interval,
                        "speed_mps": speed,
                        "occupancy_pct": occ * 100.0,
                        "length_m": 0.0,
                        "_row": rows[sel] + first - 1,
                    }
                ),
                pd.DataFrame({"samples": samples, "observed_pct": observed}),
            )
        )
    det = pd.concat([b[0] for b in blocks], ignore_index=True)
    quality = pd.concat([b[1] for b in blocks], ignore_index=True)
    order = np.lexsort((det["lane_index"], det["arc_m"], det["begin_s"]))
    det, quality = (
        det.iloc[order].reset_index(drop=True),
        quality.iloc[order].reset_index(drop=True),
    )
    quality["row"] = det.pop("_row").to_numpy()
    frame = _frame({c: det[c].to_numpy() for c in det.columns}, mapping)
    return Stations(path, "pems", frame, quality)


def _optional(df: pd.DataFrame, column: str, path: Path) -> np.ndarray:
    return (
        numbers(df, column, path, allow_nan=True)
        if column in df.columns
        else np.full(len(df), np.nan)
    )


# --------------------------------------------------------------------------- generic


def read_generic_stations(
    path: Path | str,
    section: Section,
    mapping: StationMapping = DEFAULT_MAPPING,
    columns: StationColumns = DEFAULT_COLUMNS,
) -> Stations:
    """A CSV with one row per station (and lane) and interval, named by ``columns``."""
    path = Path(path)
    df = read_table(path, dtype=str, skipinitialspace=True)
    need = [columns.station, columns.begin, columns.flow, columns.speed]
    need += [c for c in (columns.end, columns.lane, columns.occupancy, columns.samples) if c]
    require_columns(df, need, path)
    rows = np.arange(len(df))
    begin = parse_times(df[columns.begin], mapping, path, columns.begin)
    if columns.end:
        end = parse_times(df[columns.end], mapping, path, columns.end)
    else:
        end = begin + infer_interval(begin, df[columns.station].to_numpy(), path, mapping)
    _check_intervals(begin, end, path, columns.end or columns.begin, rows)
    places = _place_all(df[columns.station], mapping, section, path, columns.station)
    arcs = np.array([p.arc_m for p in places])
    if columns.lane:
        here = lanes_at(section, arcs)
        num = numbers(df, columns.lane, path)
        lane = lane_index(num, mapping.lane_numbering, mapping.first_lane, mapping.lane_count, here)
        check_on_section(
            section,
            arcs,
            lane,
            path,
            rows,
            rows + 2,
            columns.station,
            columns.lane,
            "check the mapping's lane numbering",
        )
    else:
        lane = np.array([p.lane for p in places])
    flow = numbers(df, columns.flow, path)
    count = flow if columns.flow_unit == "veh" else flow * (end - begin) / 3600.0
    speed = numbers(df, columns.speed, path, allow_nan=True) * unit(
        SPEED_UNITS, columns.speed_unit, "speed_unit", str(path)
    )
    _check_speeds(speed, path, columns.speed, columns.speed_unit, rows)
    occ = (
        numbers(df, columns.occupancy, path, allow_nan=True)
        if columns.occupancy
        else np.full(len(df), np.nan)
    )
    if columns.occupancy_unit == "fraction":
        occ = occ * 100.0
    if columns.occupancy:
        check_range(
            occ,
            0.0,
            100.0,
            path,
            columns.occupancy,
            "occupancy [%]",
            f"occupancy_unit = {columns.occupancy_unit!r}",
            rows,
        )
    frame = _frame(
        {
            "detector_id": df[columns.station].astype(str).to_numpy(),
            "kind": np.full(len(df), "e1"),
            "lane_index": lane.astype(np.int64),
            "arc_m": arcs,
            "begin_s": begin,
            "end_s": end,
            "n_veh": count,
            "flow_vph": count * 3600.0 / (end - begin),
            "speed_mps": speed,
            "occupancy_pct": occ,
            "length_m": np.zeros(len(df)),
        },
        mapping,
    )
    samples = _optional(df, columns.samples, path) if columns.samples else np.full(len(df), np.nan)
    quality = pd.DataFrame({"samples": samples, "observed_pct": np.nan, "row": rows})
    return Stations(path, "generic", frame, quality)


# --------------------------------------------------------------------------- SUMO


def detector_places(additional: Path, section: Section) -> dict[str, tuple[str, int, float, float]]:
    """kind, lane index, arc and length of every E1/E2 of a SUMO additional file; a detector
    on a lane off the section is one line naming it."""
    try:
        root = ET.parse(additional).getroot()
    except (OSError, ET.ParseError) as exc:
        raise UserError(f"{additional}: not a readable additional file ({exc})") from None
    out = {}
    for k, el in enumerate(root.iter()):
        tag = el.tag.split("}")[-1]
        if tag not in ("inductionLoop", "e1Detector", "laneAreaDetector", "e2Detector"):
            continue
        did = el.get("id", "")
        lane = (el.get("lanes", "").split() or [el.get("lane", "")])[0]
        pos = float(el.get("pos", "0"))
        hit = section.locate(lane, pos)
        if hit is None:
            raise UserError(
                f"{additional}: element {k} ({tag} {did!r}), attribute 'lane': lane {lane!r} is "
                f"not on the section ({', '.join(section.edge_ids)})"
            )
        kind = "e1" if tag in ("inductionLoop", "e1Detector") else "e2"
        length = e2_length(el, section, additional, k, did) if kind == "e2" else 0.0
        out[did] = (kind, hit[0], hit[1], length)
    return out


def read_sumo_detectors(
    path: Path | str,
    section: Section,
    additional: Path | str,
    mapping: StationMapping = DEFAULT_MAPPING,
) -> Stations:
    """SUMO E1 (``inductionLoop``) or E2 (``laneAreaDetector``) interval output, placed by the
    detector definitions in ``additional``; speeds are E1's harmonic mean (space-mean)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: missing")
    places = detector_places(Path(additional), section)
    try:
        recs = [el.attrib for el in ET.parse(path).getroot().iter("interval")]
    except ET.ParseError as exc:
        raise UserError(f"{path}: not valid XML ({exc})") from None
    if not recs:
        raise UserError(f"{path}: no <interval> element (not a SUMO detector output)")
    df = pd.DataFrame(recs)
    require_columns(df, ["id", "begin", "end"], path)
    rows = np.arange(len(df))
    for i, did in enumerate(df["id"]):
        if did not in places:
            raise UserError(
                f"{path}: interval {i + 1}, attribute 'id': detector {did!r} is not defined on the "
                f"section in {additional}"
            )
    info = [places[d] for d in df["id"]]
    kind = np.array([x[0] for x in info])
    begin, end = numbers(df, "begin", path), numbers(df, "end", path)
    _check_intervals(begin, end, path, "end", rows)
    e1 = kind == "e1"
    flow = np.full(len(df), np.nan)
    n_veh = np.zeros(len(df))
    speed = np.full(len(df), np.nan)
    occ = np.zeros(len(df))
    density = np.zeros(len(df))
    length = np.array([x[3] for x in info])
    if e1.any():
        require_columns(df, ["nVehContrib", "flow", "occupancy", "harmonicMeanSpeed"], path)
        sub = df[e1]
        flow[e1] = numbers(sub, "flow", path)
        n_veh[e1] = numbers(sub, "nVehContrib", path)
        hms = numbers(sub, "harmonicMeanSpeed", path)
        speed[e1] = np.where(hms < 0, np.nan, hms)  # SUMO writes -1 when no vehicle passed
        occ[e1] = numbers(sub, "occupancy", path)
        with np.errstate(divide="ignore", invalid="ignore"):
            density[e1] = np.where(speed[e1] > 0, flow[e1] / speed[e1] / 3.6, 0.0)
    if (~e1).any():
        require_columns(df, ["nVehSeen", "meanSpeed", "meanOccupancy", "meanVehicleNumber"], path)
        sub = df[~e1]
        n_veh[~e1] = numbers(sub, "nVehSeen", path)
        ms = numbers(sub, "meanSpeed", path)
        speed[~e1] = np.where(ms < 0, np.nan, ms)
        occ[~e1] = numbers(sub, "meanOccupancy", path)
        # SUMO counts a vehicle on an area while any part of it is there (k (l + L) at
        # density k): less the occupancy (k L) it is k l, as truth.section_detectors reads
        # its own E2 (vehicle-seconds per second where written, else meanVehicleNumber).
        if "sampledSeconds" in sub.columns:
            dur = (end - begin)[~e1]
            on = numbers(sub, "sampledSeconds", path) / np.where(dur > 0, dur, np.inf)
        else:
            on = numbers(sub, "meanVehicleNumber", path)
        density[~e1] = np.maximum(on - occ[~e1] / 100.0, 0.0) / length[~e1] * 1000.0
    _check_speeds(speed, path, "harmonicMeanSpeed", "m/s", rows)
    frame = _frame(
        {
            "detector_id": df["id"].to_numpy(),
            "kind": kind,
            "lane_index": np.array([x[1] for x in info], dtype=np.int64),
            "arc_m": np.array([x[2] for x in info]),
            "begin_s": begin + mapping.clock_offset_s,
            "end_s": end + mapping.clock_offset_s,
            "n_veh": n_veh,
            "flow_vph": flow,
            "speed_mps": speed,
            "occupancy_pct": occ,
            "density_vpkm": density,
            "length_m": length,
        },
        mapping,
    )
    quality = pd.DataFrame({"samples": np.nan, "observed_pct": np.nan, "row": rows}, index=rows)
    return Stations(path, "sumo", frame, quality)

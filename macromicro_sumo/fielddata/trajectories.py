"""Observed trajectories from field files, in the ``trajectories.csv`` schema.

Layouts: SUMO FCD XML (lane IDs and lane positions, placed by ``Section.locate``), NGSIM
(US-101 / I-80 column names, feet, 10 Hz), highD ``tracks.csv`` (metres, a frame rate and a
driving direction) and a generic CSV with a column map. Every reader returns a
``Trajectories``: the frame the pipeline takes unchanged (``observed`` True on every row),
plus what the file says about each vehicle (its length) and what was dropped.
Speeds and accelerations are the file's own; ``cleaning.clean_trajectories`` re-derives
them from noisy positions.
"""

from __future__ import annotations

import xml.sax
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.fielddata.leaders import id_strings, measured_leaders
from macromicro_sumo.fielddata.mapping import (
    TrajectoryMapping,
    check_on_section,
    lane_index,
    lanes_at,
    off_section,
    trajectory_units,
)
from macromicro_sumo.fielddata.schema import (
    LEADER_COLUMNS,
    MAX_SPEED_MPS,
    TRAJ_COLUMNS,
    check_range,
    numbers,
    read_table,
    require_columns,
    where,
)
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.data import TRAJECTORY_LAYOUT_DEFAULTS, TrajectoryColumns

NGSIM_MAPPING = TrajectoryMapping(**TRAJECTORY_LAYOUT_DEFAULTS["ngsim"])
HIGHD_MAPPING = TrajectoryMapping(frame_rate_hz=25.0)
DEFAULT_MAPPING = TrajectoryMapping()
NGSIM_CLASSES = {1: "motorcycle", 2: "auto", 3: "truck"}
# An acceleration this large is no outlier but a unit declared wrong.
MAX_FILE_ACCEL_MPS2 = 50.0


DEFAULT_COLUMNS = TrajectoryColumns()


@dataclass(frozen=True)
class Trajectories:
    """Observed trajectories of one file on the section."""

    file: Path
    layout: str
    frame: pd.DataFrame  # trajectories.csv schema, observed = True
    vehicles: pd.DataFrame  # vehicle_id, vtype, length_m (NaN: unknown), rows
    dropped_off_section: int = 0

    @property
    def leader_measured(self) -> bool:
        """Whether the layout carries the vehicles' own leader measurement (radar)."""
        return "leader_spacing_m" in self.frame.columns


def check_order(
    vehicle: np.ndarray, values: np.ndarray, path: Path, column: str, lines: np.ndarray
) -> None:
    """Within each vehicle, ``values`` (frames, times) strictly increase in file order: a
    repeated or backward frame is one line naming the row."""
    codes = pd.factorize(pd.Series(vehicle))[0]
    order = np.argsort(codes, kind="stable")
    same = codes[order][1:] == codes[order][:-1]
    step = np.diff(values[order])
    bad = np.flatnonzero(same & (step <= 0))
    if bad.size:
        k = int(order[bad[0] + 1])
        prev = values[order[bad[0]]]
        what = "repeats" if values[k] == prev else "goes back from"
        raise UserError(
            f"{where(path, k, column, int(lines[k]))}: vehicle {vehicle[k]!s} {what} "
            f"{prev:g} to {values[k]:g}; accepted: strictly increasing per vehicle "
            "(one row per vehicle and frame, in time order)"
        )


def derive_rates(vehicle: np.ndarray, time_s: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Rate of change of ``x`` per vehicle: central differences inside, one-sided at the
    ends (rows in file order, per vehicle increasing in time)."""
    rate = np.zeros(len(x))
    codes = pd.factorize(pd.Series(vehicle))[0]
    for idx in pd.Series(np.arange(len(x))).groupby(codes).indices.values():
        if len(idx) > 1:
            rate[idx] = np.gradient(x[idx], time_s[idx])
    return rate


def place(
    raw: pd.DataFrame,
    cols: dict[str, str],
    m: TrajectoryMapping,
    section: Section,
    path: Path,
    layout: str,
    outside: str = "error",
) -> Trajectories:
    """The section frame of a raw table (row, line, vehicle_id, vtype, time, pos, lane,
    speed, accel, length in file units; speed/accel NaN: derive). ``cols`` names each
    field's file column for messages; ``outside``: "error" or "drop" rows off the section."""
    lu, su, au, tu = trajectory_units(m, str(path))
    rows, lines = raw["row"].to_numpy(), raw["line"].to_numpy()
    vid = raw["vehicle_id"].astype(str).to_numpy()
    vtypes = raw["vtype"].astype(str).to_numpy()
    t = raw["time"].to_numpy(dtype=float) * tu + m.clock_offset_s
    check_order(vid, t, path, cols["time"], lines)
    arc = m.offset_m + m.direction * raw["pos"].to_numpy(dtype=float) * lu
    arc = section.wrap(arc)
    here = lanes_at(section, np.clip(arc, 0.0, section.length_m))
    lane = lane_index(raw["lane"].to_numpy(), m.lane_numbering, m.first_lane, m.lane_count, here)
    hint = (
        f"check offset_m = {m.offset_m:g}, direction = {m.direction}, length_unit = "
        f"{m.length_unit!r}, lane_numbering = {m.lane_numbering!r}, first_lane = {m.first_lane}"
    )
    dropped = 0
    if outside == "drop":
        keep = ~off_section(section, arc, lane)
        dropped = int((~keep).sum())
        raw, rows, lines, vid, vtypes = raw[keep], rows[keep], lines[keep], vid[keep], vtypes[keep]
        t, arc, lane = t[keep], arc[keep], lane[keep]
        if raw.empty:
            raise UserError(f"{path}: no row on the section; {hint}")
    check_on_section(section, arc, lane, path, rows, lines, cols["pos"], cols["lane"], hint)
    speed = raw["speed"].to_numpy(dtype=float) * su
    if np.isnan(speed).all():
        speed = derive_rates(vid, t, arc)  # no speed column: from positions
    check_range(
        speed,
        0.0,
        MAX_SPEED_MPS,
        path,
        cols["speed"],
        "speed [m/s]",
        f"is speed_unit = {m.speed_unit!r} right (ft/s read as m/s is 3.3 times too fast, "
        f"km/h 3.6 times), and direction = {m.direction}?",
        rows,
        lines,
    )
    accel = raw["accel"].to_numpy(dtype=float) * au
    if np.isnan(accel).all():
        accel = derive_rates(vid, t, speed)
    check_range(
        accel,
        -MAX_FILE_ACCEL_MPS2,
        MAX_FILE_ACCEL_MPS2,
        path,
        cols["accel"],
        "acceleration [m/s^2]",
        f"is accel_unit = {m.accel_unit!r} right?",
        rows,
        lines,
    )
    lead = measured_leaders(raw, vid, speed, lu, su, path, cols, rows, lines)
    frame = pd.DataFrame(
        {
            "run": m.run,
            "time_s": t,
            "vehicle_id": vid,
            "vtype": vtypes,
            "observed": True,
            "lane_index": lane.astype(np.int64),
            "edge_index": section.edge_index(arc).astype(np.int64),
            "arc_m": arc,
            "speed_mps": speed,
            "accel_mps2": accel,
        }
    )[list(TRAJ_COLUMNS)]
    if lead is not None:
        frame = frame.assign(**dict(zip(LEADER_COLUMNS, lead, strict=True)))
    frame = frame.sort_values(["time_s", "lane_index", "arc_m"], kind="stable")
    length = raw["length"].to_numpy(dtype=float) * lu
    vehicles = (
        pd.DataFrame({"vehicle_id": vid, "vtype": vtypes, "length_m": length})
        .groupby("vehicle_id", sort=False)
        .agg(vtype=("vtype", "first"), length_m=("length_m", "median"), rows=("vtype", "size"))
        .reset_index()
    )
    return Trajectories(path, layout, frame.reset_index(drop=True), vehicles, dropped)


def _raw(df: pd.DataFrame, **columns: np.ndarray | pd.Series | float | str) -> pd.DataFrame:
    """A raw table in file order with CSV row and line numbers."""
    out = pd.DataFrame({"row": np.arange(len(df)), "line": np.arange(len(df)) + 2})
    for name, values in columns.items():
        out[name] = values.to_numpy() if isinstance(values, pd.Series) else values
    return out


def read_ngsim(
    path: Path | str,
    section: Section,
    mapping: TrajectoryMapping = NGSIM_MAPPING,
    outside: str = "error",
) -> Trajectories:
    """An NGSIM trajectory file (``Vehicle_ID, Frame_ID, Global_Time`` [ms], ``Local_Y``
    [ft] front bumper along the road, ``Lane_ID`` 1 = leftmost, ``v_Vel`` [ft/s], ``v_Acc``
    [ft/s^2], ``v_Length`` [ft], ``v_Class``); the time is ``Global_Time``."""
    path = Path(path)
    df = read_table(path, skipinitialspace=True)
    need = ["Vehicle_ID", "Frame_ID", "Global_Time", "Local_Y", "Lane_ID", "v_Vel", "v_Acc"]
    require_columns(df, need, path)
    values = {c: numbers(df, c, path) for c in need[1:]}
    lines = np.arange(len(df)) + 2
    check_order(
        df["Vehicle_ID"].astype(str).to_numpy(), values["Frame_ID"], path, "Frame_ID", lines
    )
    vclass = (
        pd.to_numeric(df["v_Class"], errors="coerce").map(NGSIM_CLASSES).fillna(mapping.vtype)
        if "v_Class" in df.columns
        else mapping.vtype
    )
    length = numbers(df, "v_Length", path) if "v_Length" in df.columns else np.nan
    raw = _raw(
        df,
        vehicle_id=df["Vehicle_ID"].astype(str),
        vtype=vclass,
        time=values["Global_Time"],
        pos=values["Local_Y"],
        lane=values["Lane_ID"],
        speed=values["v_Vel"],
        accel=values["v_Acc"],
        length=length,
    )
    # The instrumented vehicle's own leader: Preceding (0: none), Space_Headway [ft] front
    # to front; NGSIM gives no leader speed (the cleaning derives it from the gap).
    if "Space_Headway" in df.columns:
        raw["lead_spacing"] = numbers(df, "Space_Headway", path)
        if "Preceding" in df.columns:
            raw["lead_id"] = pd.to_numeric(df["Preceding"], errors="coerce").fillna(0)
            raw["lead_id"] = raw["lead_id"].astype(np.int64).astype(str).to_numpy()
    cols = {"time": "Global_Time", "pos": "Local_Y", "lane": "Lane_ID"}
    cols |= {"lead_spacing": "Space_Headway"}
    return place(
        raw, {**cols, "speed": "v_Vel", "accel": "v_Acc"}, mapping, section, path, "ngsim", outside
    )


def read_highd(
    path: Path | str,
    section: Section,
    mapping: TrajectoryMapping = HIGHD_MAPPING,
    outside: str = "error",
) -> Trajectories:
    """A highD ``tracks.csv`` (``frame, id, x, width, xVelocity, xAcceleration, laneId``;
    metres; ``x`` is the bounding box's rear-left corner, ``width`` its length along x).
    ``mapping.direction``: +1 for vehicles driving towards growing x (highD's driving
    direction 2), -1 towards falling x (direction 1); speeds are signed along x."""
    path = Path(path)
    df = read_table(path)
    need = ["frame", "id", "x", "xVelocity", "xAcceleration", "laneId"]
    require_columns(df, need, path)
    values = {c: numbers(df, c, path) for c in need}
    lines = np.arange(len(df)) + 2
    check_order(df["id"].astype(str).to_numpy(), values["frame"], path, "frame", lines)
    width = numbers(df, "width", path) if "width" in df.columns else np.zeros(len(df))
    # The front bumper: the box's far end when driving towards growing x, else x itself.
    front = values["x"] + (width if mapping.direction > 0 else 0.0)
    raw = _raw(
        df,
        vehicle_id=df["id"].astype(str),
        vtype=mapping.vtype,
        time=values["frame"] / mapping.frame_rate_hz / trajectory_units(mapping, str(path))[3],
        pos=front,
        lane=values["laneId"],
        speed=mapping.direction * values["xVelocity"],
        accel=mapping.direction * values["xAcceleration"],
        length=width if "width" in df.columns else np.nan,
    )
    # highD's own leader: precedingId (0: none), dhw [m] bumper to bumper,
    # precedingXVelocity [m/s] signed along x like xVelocity.
    if "dhw" in df.columns:
        raw["lead_gap"] = numbers(df, "dhw", path)
        if "precedingId" in df.columns:
            raw["lead_id"] = pd.to_numeric(df["precedingId"], errors="coerce").fillna(0)
            raw["lead_id"] = raw["lead_id"].astype(np.int64).astype(str).to_numpy()
        if "precedingXVelocity" in df.columns:
            raw["lead_speed"] = mapping.direction * numbers(df, "precedingXVelocity", path)
    cols = {"time": "frame", "pos": "x", "lane": "laneId", "speed": "xVelocity"}
    cols |= {"lead_gap": "dhw", "lead_speed": "precedingXVelocity"}
    return place(raw, {**cols, "accel": "xAcceleration"}, mapping, section, path, "highd", outside)


def read_generic_trajectories(
    path: Path | str,
    section: Section,
    mapping: TrajectoryMapping = DEFAULT_MAPPING,
    columns: TrajectoryColumns = DEFAULT_COLUMNS,
    outside: str = "error",
) -> Trajectories:
    """A CSV with one row per vehicle and time, its columns named by ``columns``, its units
    and coordinates by ``mapping``."""
    path = Path(path)
    df = read_table(path)
    need = [columns.vehicle_id, columns.time, columns.position, columns.lane]
    leader = (columns.leader_id, columns.spacing, columns.gap, columns.leader_speed)
    optional = [c for c in (columns.speed, columns.accel, columns.length, *leader) if c]
    optional += [columns.delta_v] if columns.delta_v else []
    require_columns(df, need + optional, path)

    def col(name: str) -> np.ndarray | float:
        return numbers(df, name, path) if name else np.nan

    raw = _raw(
        df,
        vehicle_id=id_strings(df[columns.vehicle_id]),
        vtype=df[columns.vtype].astype(str) if columns.vtype else mapping.vtype,
        time=col(columns.time),
        pos=col(columns.position),
        lane=col(columns.lane),
        speed=col(columns.speed),
        accel=col(columns.accel),
        length=col(columns.length),
    )
    # The vehicle's own leader measurement, where the column map names one.
    for key, name in (
        ("lead_spacing", columns.spacing),
        ("lead_gap", "" if columns.spacing else columns.gap),
        ("lead_speed", columns.leader_speed),
        ("lead_dv", "" if columns.leader_speed else columns.delta_v),
    ):
        if name:
            raw[key] = numbers(df, name, path, allow_nan=True)
    if columns.leader_id:
        raw["lead_id"] = id_strings(df[columns.leader_id])
    cols = {"time": columns.time, "pos": columns.position, "lane": columns.lane}
    cols |= {"speed": columns.speed or columns.position, "accel": columns.accel or columns.time}
    cols |= {"lead_spacing": columns.spacing, "lead_gap": columns.gap}
    cols |= {"lead_speed": columns.leader_speed or columns.delta_v}
    return place(raw, cols, mapping, section, path, "generic", outside)


class _FcdHandler(xml.sax.ContentHandler):
    """Collects ``<vehicle>`` attributes of an FCD file with the line each stands on."""

    def __init__(self) -> None:
        super().__init__()
        self.time = float("nan")
        self.rows: list[tuple] = []

    def startElement(self, name: str, attrs: xml.sax.xmlreader.AttributesImpl) -> None:  # noqa: N802
        if name == "timestep":
            self.time = attrs.get("time", "nan")
        elif name in ("vehicle", "person", "container"):
            line = self._locator.getLineNumber() if self._locator else 0
            self.rows.append(
                (
                    line,
                    self.time,
                    attrs.get("id"),
                    attrs.get("type", ""),
                    attrs.get("lane"),
                    attrs.get("pos"),
                    attrs.get("speed"),
                    attrs.get("acceleration", "nan"),
                )
            )


def read_fcd(
    path: Path | str,
    section: Section,
    mapping: TrajectoryMapping = DEFAULT_MAPPING,
    outside: str = "error",
) -> Trajectories:
    """SUMO floating-car data (``--fcd-output``): ``<timestep time><vehicle id type lane pos
    speed [acceleration]>``; lanes are placed by ``Section.locate``. Vehicles on lanes off the
    section are an error (``outside = "drop"``: dropped and counted)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: missing")
    handler = _FcdHandler()
    try:
        xml.sax.parse(str(path), handler)
    except xml.sax.SAXParseException as exc:
        raise UserError(
            f"{path}: line {exc.getLineNumber()}: not valid XML ({exc.getMessage()})"
        ) from None
    cols = ["line", "time", "id", "type", "lane", "pos", "speed", "acceleration"]
    df = pd.DataFrame(handler.rows, columns=cols)
    if df.empty:
        raise UserError(f"{path}: no <vehicle> in any <timestep>")
    lines = df["line"].to_numpy()
    for c in ("id", "lane", "pos", "speed"):
        miss = np.flatnonzero(df[c].isna().to_numpy())
        if miss.size:
            i = int(miss[0])
            raise UserError(
                f"{where(path, i, c, int(lines[i]))}: attribute missing (write FCD with SUMO's "
                "default attributes: id, lane, pos, speed)"
            )
    values = {c: numbers(df, c, path, allow_nan=c == "acceleration") for c in cols[1:2] + cols[5:]}
    hits = [section.locate(lane, 0.0) for lane in df["lane"]]
    on = np.array([h is not None for h in hits])
    if not on.all() and outside != "drop":
        i = int(np.flatnonzero(~on)[0])
        raise UserError(
            f"{where(path, i, 'lane', int(lines[i]))}: lane {df['lane'].iloc[i]!r} is not on the "
            f"section ({', '.join(section.edge_ids)}); accepted: its lanes and junction lanes"
        )
    arc = np.array(
        [
            section.locate(ln, p)[1] if h else np.nan
            for ln, p, h in zip(df["lane"], values["pos"], on, strict=True)
        ]
    )
    lane = np.array([h[0] if h else -1 for h in hits])
    raw = _raw(
        df,
        vehicle_id=df["id"].astype(str),
        vtype=df["type"].replace("", mapping.vtype).astype(str),
        time=values["time"],
        pos=arc,
        lane=lane,
        speed=values["speed"],
        accel=values["acceleration"],
        length=np.nan,
    )
    raw["row"], raw["line"] = np.arange(len(df)), lines
    raw = raw[on]
    # Positions are already section coordinates: an identity mapping with the file's clock.
    ident = TrajectoryMapping(
        clock_offset_s=mapping.clock_offset_s, run=mapping.run, vtype=mapping.vtype
    )
    cols_map = {
        "time": "time",
        "pos": "pos",
        "lane": "lane",
        "speed": "speed",
        "accel": "acceleration",
    }
    out = place(raw, cols_map, ident, section, path, "fcd", outside)
    return Trajectories(
        out.file, out.layout, out.frame, out.vehicles, int((~on).sum()) + out.dropped_off_section
    )

"""``[data]``: field data instead of a simulated ground truth (docs/field-data.md).

The one definition of how a field file lands on the section: its conventions (coordinates,
units, lane numbering, clock), the column names of the generic CSV layouts, the stations'
places and the cleaning. ``fielddata`` builds on these classes (its mappings add the run a
file's rows get); the scenario's ``[data]`` tables are built from them, so a key, its default
and its range are written once. Each layout's own conventions are filled in before the table
is checked, so the scenario holds the values in effect (NGSIM: feet, lanes from the left).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fields import build_table, spec

# Conversion factors to SI (exact by definition of the foot and the mile).
FT = 0.3048
MILE = 1609.344
LENGTH_UNITS = {"m": 1.0, "ft": FT, "km": 1000.0, "mi": MILE}
SPEED_UNITS = {"m/s": 1.0, "ft/s": FT, "km/h": 1 / 3.6, "mph": MILE / 3600.0}
ACCEL_UNITS = {"m/s^2": 1.0, "ft/s^2": FT}
TIME_UNITS = {"s": 1.0, "ms": 1e-3}
# Harder than any tyre can brake or any car can accelerate: beyond it a sample is an outlier.
MAX_ACCEL_MPS2 = 10.0

TRAJECTORY_LAYOUTS = ("fcd", "ngsim", "highd", "generic")
STATION_LAYOUTS = ("sumo", "pems", "generic")
DATA_SOURCES = ("simulate", "files")
TRAJECTORY_LAYOUT_DEFAULTS: dict[str, dict[str, Any]] = {
    "ngsim": {
        "lane_numbering": "left",
        "first_lane": 1,
        "length_unit": "ft",
        "speed_unit": "ft/s",
        "accel_unit": "ft/s^2",
        "time_unit": "ms",
    },
}
STATION_LAYOUT_DEFAULTS: dict[str, dict[str, Any]] = {
    "pems": {"lane_numbering": "left", "first_lane": 1},
}
CLEANING_LAYOUT_DEFAULTS: dict[str, dict[str, Any]] = {"ngsim": {"smoother": "ema"}}


@dataclass(frozen=True, kw_only=True)
class TrajectoryConventions:
    """A trajectory file's coordinates, units and clock -> the section's."""

    offset_m: float = spec(0.0, lo=-1e7, hi=1e7, doc="section arc of the file's position 0 [m]")
    direction: int = spec(
        1, lo=-1, hi=1, accepted="1 or -1", doc="+1: positions grow along the section; -1: against"
    )
    lane_numbering: str = spec(
        "right", choices=("right", "left"), doc="the files count lanes from the right or the left"
    )
    first_lane: int = spec(0, lo=-100, hi=100, doc="the files' number of their first lane")
    lane_count: int = spec(
        0, lo=0, hi=64, doc="lanes counted from the left: road width (0: the section's lanes there)"
    )
    length_unit: str = spec("m", choices=tuple(LENGTH_UNITS), doc="unit of positions")
    speed_unit: str = spec("m/s", choices=tuple(SPEED_UNITS), doc="unit of speeds")
    accel_unit: str = spec("m/s^2", choices=tuple(ACCEL_UNITS), doc="unit of accelerations")
    time_unit: str = spec("s", choices=tuple(TIME_UNITS), doc="unit of the files' times")
    clock_offset_s: float = spec(
        0.0, lo=-1e13, hi=1e13, doc="added to every time after unit conversion [s]"
    )
    frame_rate_hz: float = spec(25.0, lo=0.01, hi=1000.0, doc="frames per second (highD)")
    vtype: str = spec("observed", doc="vtype of vehicles whose file names none")


@dataclass(frozen=True, kw_only=True)
class TrajectoryColumns:
    """Column names of a generic trajectory CSV ("": the file has no such column)."""

    vehicle_id: str = spec("vehicle_id", doc="vehicle ID column")
    time: str = spec("time_s", doc="time column (unit: time_unit)")
    position: str = spec("position_m", doc="position along the road (length_unit)")
    lane: str = spec("lane", doc="lane number (lane_numbering, first_lane)")
    speed: str = spec("speed_mps", doc="speed column ('': derived from positions)")
    accel: str = spec("accel_mps2", doc="acceleration column ('': derived from speeds)")
    vtype: str = spec("", doc="vehicle type column ('': vtype)")
    length: str = spec("", doc="vehicle length column (length_unit; '': unknown)")
    leader_id: str = spec(
        "", doc="measured leader's vehicle ID column ('': none; 0 or empty: no leader)"
    )
    spacing: str = spec(
        "", doc="measured front-to-front spacing to the leader (length_unit; '': none)"
    )
    gap: str = spec(
        "", doc="measured bumper gap to the leader (length_unit; '': none; used without spacing)"
    )
    leader_speed: str = spec("", doc="measured leader speed (speed_unit; '': none)")
    delta_v: str = spec(
        "", doc="own minus leader speed (speed_unit; '': none; used without leader_speed)"
    )


@dataclass(frozen=True, kw_only=True)
class TrajectoryDataConfig(TrajectoryConventions):
    """Observed vehicles' trajectories (the micro data): one file per run (recording)."""

    layout: str = spec("generic", choices=TRAJECTORY_LAYOUTS, doc="file layout")
    files: list[str] = spec([], doc="one file per run, relative to the scenario file")
    outside: str = spec(
        "error", choices=("error", "drop"), doc="rows off the section: refuse, or drop and count"
    )
    columns: TrajectoryColumns = spec(TrajectoryColumns())


@dataclass(frozen=True, kw_only=True)
class StationPlace:
    """One station (detector) of the station files on the section."""

    id: str = spec(doc="station ID as the files write it")
    arc_m: float = spec(lo=-1e7, hi=1e7, doc="section arc of the station [m]")
    lane: int = spec(
        -1, lo=-1, hi=63, doc="lane index from the right; -1: the file's own lane numbers"
    )


@dataclass(frozen=True, kw_only=True)
class StationConventions:
    """A station file's stations, lane numbering and clock -> the section's."""

    stations: tuple[StationPlace, ...] = ()  # [{id, arc_m, lane}, ...]; see build_data
    lane_numbering: str = spec(
        "right", choices=("right", "left"), doc="the files count lanes from the right or the left"
    )
    first_lane: int = spec(0, lo=-100, hi=100, doc="the files' number of their first lane")
    lane_count: int = spec(
        0, lo=0, hi=64, doc="lanes counted from the left: road width (0: the section's lanes there)"
    )
    clock_origin: str = spec("", doc="ISO date-time that is t = 0 s of the section's clock")
    clock_offset_s: float = spec(0.0, lo=-1e13, hi=1e13, doc="added to every time [s]")
    interval_s: float = spec(0.0, lo=0.0, hi=86400.0, doc="interval length [s] (0: from data)")

    def place(self, station: str) -> StationPlace | None:
        """Where ``station`` is on the section (None: not placed)."""
        for s in self.stations:
            if s.id == station:
                return s
        return None


@dataclass(frozen=True, kw_only=True)
class StationColumns:
    """Column names and units of a generic station CSV ("": the file has no such column)."""

    station: str = spec("station", doc="station ID column")
    begin: str = spec("begin_s", doc="interval start: seconds or a date-time")
    end: str = spec("", doc="interval end ('': begin + interval_s)")
    lane: str = spec("", doc="lane number column ('': the station's lane, or all lanes)")
    flow: str = spec("flow", doc="flow column")
    flow_unit: str = spec("veh/h", choices=("veh/h", "veh"), doc="veh/h, or vehicles per interval")
    speed: str = spec("speed", doc="mean speed column (empty cell: no vehicle)")
    speed_unit: str = spec("m/s", choices=tuple(SPEED_UNITS), doc="unit of speeds")
    occupancy: str = spec("", doc="occupancy column ('': unknown)")
    occupancy_unit: str = spec("%", choices=("%", "fraction"), doc="percent or fraction 0-1")
    samples: str = spec("", doc="samples per interval ('': unknown)")


@dataclass(frozen=True, kw_only=True)
class StationDataConfig(StationConventions):
    """Station (detector) data (the macro data): one file per run, as the trajectories."""

    layout: str = spec("generic", choices=STATION_LAYOUTS, doc="file layout")
    files: list[str] = spec([], doc="one file per run, relative to the scenario file")
    additional: list[str] = spec(
        [], doc="SUMO layout: the additional file placing the detectors (one, or one per file)"
    )
    columns: StationColumns = spec(StationColumns())


@dataclass(frozen=True, kw_only=True)
class CleaningConfig:
    """How the field data is cleaned (docs/field-data.md; NGSIM: smoother = "ema")."""

    smoother: str = spec(
        "none",
        choices=("none", "ema"),
        doc="re-derive speeds and accelerations from positions: 'ema' (Thiemann et al. 2008)",
    )
    position_width_s: float = spec(0.5, lo=0.0, hi=60.0, doc="sEMA width T for positions [s]")
    speed_width_s: float = spec(0.5, lo=0.0, hi=60.0, doc="sEMA width T for speeds [s]")
    accel_width_s: float = spec(1.0, lo=0.0, hi=60.0, doc="sEMA width T for accelerations [s]")
    max_accel_mps2: float = spec(
        MAX_ACCEL_MPS2, lo=0.1, hi=50.0, doc="|a| beyond this is an outlier [m/s^2]"
    )
    gap_factor: float = spec(
        3.0, lo=1.01, hi=1000.0, doc="a step longer than this many sampling periods is a gap"
    )
    min_samples: float = spec(
        0.0, lo=0.0, hi=1e6, doc="station intervals with fewer samples are excluded"
    )
    min_observed_pct: float = spec(
        50.0, lo=0.0, hi=100.0, doc="PeMS: intervals observed less than this [%] are excluded"
    )


@dataclass(frozen=True, kw_only=True)
class DataConfig:
    """Where the micro and macro data come from: a simulated ground truth or files."""

    source: str = spec(
        "simulate",
        choices=DATA_SOURCES,
        doc="'simulate': SUMO runs the demand (ground truth); 'files': field data",
    )
    trajectories: TrajectoryDataConfig = spec(TrajectoryDataConfig())
    stations: StationDataConfig = spec(StationDataConfig())
    cleaning: CleaningConfig = spec(CleaningConfig())


def _with_layout_defaults(table: Any, defaults: dict[str, dict[str, Any]]) -> Any:
    """A raw table with its layout's conventions under the user's own keys."""
    if not isinstance(table, dict):
        return table  # build_table names the problem
    return {**defaults.get(table.get("layout", ""), {}), **table}


def build_data(table: Any, file: str) -> DataConfig:
    """``[data]`` checked, each layout's conventions filled in, stations placed."""
    if not isinstance(table, dict):
        return build_table(DataConfig, table, "data", file)
    table = dict(table)
    # build_table keeps the key ``source`` for the scenario file's path: checked here.
    source = table.pop("source", "simulate")
    choices = DATA_SOURCES
    if not isinstance(source, str) or source not in choices:
        raise UserError(
            f"{file}: data.source = {source!r} is not accepted; accepted: one of "
            + ", ".join(repr(c) for c in choices)
        )
    traj = _with_layout_defaults(table.get("trajectories", {}), TRAJECTORY_LAYOUT_DEFAULTS)
    stations = _with_layout_defaults(table.get("stations", {}), STATION_LAYOUT_DEFAULTS)
    places: Any = []
    if isinstance(stations, dict):
        stations = dict(stations)
        places = stations.pop("stations", [])
    layout = traj.get("layout", "") if isinstance(traj, dict) else ""
    cleaning = table.get("cleaning", {})
    if isinstance(cleaning, dict):
        cleaning = {**CLEANING_LAYOUT_DEFAULTS.get(layout, {}), **cleaning}
    table.update(trajectories=traj, stations=stations, cleaning=cleaning)
    cfg = build_table(DataConfig, table, "data", file)
    if not isinstance(places, list):
        raise UserError(
            f"{file}: data.stations.stations must be a list of tables {{id, arc_m, lane}}"
        )
    built = tuple(
        build_table(StationPlace, p, f"data.stations.stations[{i}]", file)
        for i, p in enumerate(places)
    )
    if len({p.id for p in built}) != len(built):
        raise UserError(f"{file}: data.stations.stations places a station id twice")
    stations_cfg = dataclasses.replace(cfg.stations, stations=built)
    return dataclasses.replace(cfg, source=source, stations=stations_cfg)


def check_data(data: DataConfig, resolve: Callable[[str], Path], k_source: str, file: str) -> None:
    """A files source names its files (one per run, each there) and cannot ask for the true
    hidden count (``k_source``): only a simulation knows it. ``resolve`` turns a path of the
    scenario file into the file's."""
    if data.source != "files":
        return
    tr, st = data.trajectories, data.stations
    for key, files in (("trajectories", tr.files), ("stations", st.files)):
        if not files:
            raise UserError(
                f"{file}: data.{key}.files is empty; accepted: one file per run with "
                "data.source = 'files'"
            )
        for value in files:
            if not resolve(value).is_file():
                raise UserError(f"{file}: data.{key}.files entry {resolve(value)} does not exist")
    if len(tr.files) != len(st.files):
        raise UserError(
            f"{file}: data.trajectories.files has {len(tr.files)} file(s), data.stations.files "
            f"{len(st.files)}; accepted: the same number (file i of each is run i)"
        )
    if st.layout == "sumo":
        if len(st.additional) not in (1, len(st.files)):
            raise UserError(
                f"{file}: data.stations.additional has {len(st.additional)} file(s); accepted: "
                f"1 or {len(st.files)} (one per station file) with layout = 'sumo'"
            )
        for value in st.additional:
            if not resolve(value).is_file():
                raise UserError(
                    f"{file}: data.stations.additional entry {resolve(value)} does not exist"
                )
    elif st.additional:
        raise UserError(
            f"{file}: data.stations.additional is for layout = 'sumo', not {st.layout!r}"
        )
    if st.layout != "sumo" and not st.stations:
        raise UserError(
            f"{file}: data.stations.stations is empty; accepted: [{{id, arc_m, lane}}, ...] "
            f"placing every station of the {st.layout} files on the section"
        )
    if tr.direction not in (1, -1):
        raise UserError(f"{file}: data.trajectories.direction = {tr.direction}; accepted: 1, -1")
    if k_source == "truth":
        raise UserError(
            f"{file}: generator.k_source = 'truth' needs a simulated ground truth; accepted "
            "'estimate' with data.source = 'files' (the hidden count of field data is unknown)"
        )

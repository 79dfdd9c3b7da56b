"""Scenarios on a user's own SUMO network: ``[network] kind = "sumo"`` plus a road section.

The ring scenario (``scenario.ring.Scenario``) draws its own IDM fleet; here SUMO runs the user's
network, demand and vehicle types, and the method works on a section of it: a list of
connected edges in driving order (an open corridor) or a closed loop. The tables reuse the
ring's typed-field machinery, so errors read the same (file, key, accepted range).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fields import ScenarioFile, build_table, spec
from macromicro_sumo.scenario.stages import (
    DeployConfig,
    EvaluationConfig,
    PolicyConfig,
    check_deploy,
)


@dataclass(frozen=True, kw_only=True)
class SumoNetworkConfig:
    """The user's SUMO files: a .sumocfg, or a net plus route and additional files."""

    kind: str = spec("sumo", choices=("ring", "sumo"), doc="network kind")
    sumocfg: str = spec("", doc="SUMO configuration (.sumocfg), relative to the scenario file")
    net_file: str = spec("", doc="SUMO .net.xml (when no sumocfg, or to override it)")
    route_files: list[str] = spec([], doc="route files with the demand (vTypes, routes, flows)")
    additional_files: list[str] = spec([], doc="additional files (detectors, rerouters, ...)")


@dataclass(frozen=True, kw_only=True)
class SectionConfig:
    """The road section the method runs on."""

    edges: list[str] = spec(doc="edge IDs in driving order; consecutive edges must be connected")
    closed: bool = spec(False, doc="true: the last edge leads back to the first (a loop)")


@dataclass(frozen=True, kw_only=True)
class InstrumentedConfig:
    """Which vehicles are observed in detail (micro data): one of three ways."""

    # Range (0, 1] is checked in _check: the typed ranges are closed intervals.
    penetration: float = spec(
        0.1, accepted="(0, 1]", doc="share of vehicles with full trajectories, in (0, 1]"
    )
    vtype: str = spec("", doc="instead: every vehicle of this vType is instrumented")
    ids: list[str] = spec([], doc="instead: exactly these vehicle IDs are instrumented")


@dataclass(frozen=True, kw_only=True)
class SectionSimulationConfig:
    """How SUMO runs the user's demand for the ground truth."""

    step_length_s: float = spec(0.5, lo=0.01, hi=5.0, doc="SUMO step length = policy step dt [s]")
    warmup_s: float = spec(300.0, lo=0.0, hi=1e6, doc="simulated before recording starts [s]")
    duration_s: float = spec(600.0, lo=1.0, hi=1e6, doc="recorded duration of each run [s]")
    n_runs: int = spec(4, lo=1, hi=10_000, doc="runs, each with its own SUMO seed")


@dataclass(frozen=True, kw_only=True)
class SectionDetectorConfig:
    """Loop detectors on the section: the user's own, or placed by the tool."""

    interval_s: float = spec(60.0, lo=1.0, hi=1e6, doc="aggregation interval [s]")
    use_user: bool = spec(True, doc="use the E1/E2 detectors of the user's files on the section")
    auto_spacing_m: float = spec(
        250.0,
        lo=0.0,
        hi=1e5,
        doc="place E1 loops on every lane at this spacing when the section has none (0: off)",
    )
    k_window_s: float = spec(
        60.0,
        lo=0.0,
        hi=1e6,
        doc="the hidden-count estimate averages detector density over this window [s]",
    )


@dataclass(frozen=True, kw_only=True)
class SectionBoundsConfig:
    """Bounds that cannot be measured: actions and the safety gap."""

    accel_mps2: tuple[float, float] = spec(
        (-4.5, 2.6), lo=-50.0, hi=50.0, doc="action bounds [a_min, a_max] [m/s^2]"
    )
    min_gap_m: float = spec(2.0, lo=0.0, hi=100.0, doc="smallest admissible bumper gap [m]")


@dataclass(frozen=True, kw_only=True)
class SectionGeneratorConfig:
    """Stage I on a section: lanes, open ends and an unknown hidden count."""

    k_source: str = spec(
        "estimate",
        choices=("estimate", "truth"),
        doc="hidden count: estimated from detector density (the default), or the simulation's truth",
    )
    t_max: int = spec(20, lo=1, hi=10_000, doc="max trials per hidden vehicle T_max")
    lambda_v: float = spec(0.5, lo=0.0, hi=1e6, doc="speed penalty weight lambda_v")
    lambda_d: float = spec(0.5, lo=0.0, hi=1e6, doc="spacing penalty weight lambda_d")
    snapshot_every_s: float = spec(10.0, lo=0.01, hi=1e6, doc="time between snapshots [s]")
    held_out_fraction: float = spec(0.25, lo=0.01, hi=0.99, doc="share of runs held out")
    hidden_size: int = spec(64, lo=4, hi=4096, doc="MLP width")
    epochs: int = spec(100, lo=1, hi=100_000, doc="max training epochs")
    batch_size: int = spec(64, lo=1, hi=1_000_000, doc="snapshots per batch")
    lr: float = spec(3e-3, lo=1e-7, hi=1.0, doc="Adam learning rate")
    patience: int = spec(15, lo=1, hi=100_000, doc="early-stopping patience [epochs]")


# --------------------------------------------------------------------------- [data]
# Field data instead of a simulated ground truth (docs/field-data.md). The keys mirror
# fielddata's TrajectoryMapping, TrajectoryColumns, StationMapping, StationColumns and
# CleaningConfig (this package ranks below fielddata, so they are declared here; a test
# checks that both agree). Each layout's own conventions are filled in before the table
# is checked, so the scenario holds the values in effect (NGSIM: feet, lanes from the left).

LENGTH_UNITS = ("m", "ft", "km", "mi")
SPEED_UNITS = ("m/s", "ft/s", "km/h", "mph")
ACCEL_UNITS = ("m/s^2", "ft/s^2")
TIME_UNITS = ("s", "ms")
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
class TrajectoryColumnsConfig:
    """Column names of a generic trajectory CSV ("": the file has no such column)."""

    vehicle_id: str = spec("vehicle_id", doc="vehicle ID column")
    time: str = spec("time_s", doc="time column (unit: time_unit)")
    position: str = spec("position_m", doc="position along the road (length_unit)")
    lane: str = spec("lane", doc="lane number (lane_numbering, first_lane)")
    speed: str = spec("speed_mps", doc="speed column ('': derived from positions)")
    accel: str = spec("accel_mps2", doc="acceleration column ('': derived from speeds)")
    vtype: str = spec("", doc="vehicle type column ('': vtype)")
    length: str = spec("", doc="vehicle length column (length_unit; '': unknown)")


@dataclass(frozen=True, kw_only=True)
class TrajectoryDataConfig:
    """Observed vehicles' trajectories (the micro data): one file per run (recording)."""

    layout: str = spec("generic", choices=TRAJECTORY_LAYOUTS, doc="file layout")
    files: list[str] = spec([], doc="one file per run, relative to the scenario file")
    outside: str = spec(
        "error", choices=("error", "drop"), doc="rows off the section: refuse, or drop and count"
    )
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
    length_unit: str = spec("m", choices=LENGTH_UNITS, doc="unit of positions")
    speed_unit: str = spec("m/s", choices=SPEED_UNITS, doc="unit of speeds")
    accel_unit: str = spec("m/s^2", choices=ACCEL_UNITS, doc="unit of accelerations")
    time_unit: str = spec("s", choices=TIME_UNITS, doc="unit of the files' times")
    clock_offset_s: float = spec(
        0.0, lo=-1e13, hi=1e13, doc="added to every time after unit conversion [s]"
    )
    frame_rate_hz: float = spec(25.0, lo=0.01, hi=1000.0, doc="frames per second (highD)")
    vtype: str = spec("observed", doc="vtype of vehicles whose file names none")
    columns: TrajectoryColumnsConfig = spec(TrajectoryColumnsConfig())


@dataclass(frozen=True, kw_only=True)
class StationPlaceConfig:
    """One station of the station files on the section."""

    id: str = spec(doc="station ID as the files write it")
    arc_m: float = spec(lo=-1e7, hi=1e7, doc="section arc of the station [m]")
    lane: int = spec(
        -1, lo=-1, hi=63, doc="lane index from the right; -1: the file's own lane numbers"
    )


@dataclass(frozen=True, kw_only=True)
class StationColumnsConfig:
    """Column names and units of a generic station CSV ("": the file has no such column)."""

    station: str = spec("station", doc="station ID column")
    begin: str = spec("begin_s", doc="interval start: seconds or a date-time")
    end: str = spec("", doc="interval end ('': begin + interval_s)")
    lane: str = spec("", doc="lane number column ('': the station's lane, or all lanes)")
    flow: str = spec("flow", doc="flow column")
    flow_unit: str = spec("veh/h", choices=("veh/h", "veh"), doc="veh/h, or vehicles per interval")
    speed: str = spec("speed", doc="mean speed column (empty cell: no vehicle)")
    speed_unit: str = spec("m/s", choices=SPEED_UNITS, doc="unit of speeds")
    occupancy: str = spec("", doc="occupancy column ('': unknown)")
    occupancy_unit: str = spec("%", choices=("%", "fraction"), doc="percent or fraction 0-1")
    samples: str = spec("", doc="samples per interval ('': unknown)")


@dataclass(frozen=True, kw_only=True)
class StationDataConfig:
    """Station (detector) data (the macro data): one file per run, as the trajectories."""

    layout: str = spec("generic", choices=STATION_LAYOUTS, doc="file layout")
    files: list[str] = spec([], doc="one file per run, relative to the scenario file")
    additional: list[str] = spec(
        [], doc="SUMO layout: the additional file placing the detectors (one, or one per file)"
    )
    stations: tuple[StationPlaceConfig, ...] = ()  # [{id, arc_m, lane}, ...]; see build_data
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
    columns: StationColumnsConfig = spec(StationColumnsConfig())


@dataclass(frozen=True, kw_only=True)
class CleaningDataConfig:
    """How the field data is cleaned (docs/field-data.md; NGSIM: smoother = "ema")."""

    smoother: str = spec(
        "none",
        choices=("none", "ema"),
        doc="re-derive speeds and accelerations from positions: 'ema' (Thiemann et al. 2008)",
    )
    position_width_s: float = spec(0.5, lo=0.0, hi=60.0, doc="sEMA width T for positions [s]")
    speed_width_s: float = spec(0.5, lo=0.0, hi=60.0, doc="sEMA width T for speeds [s]")
    accel_width_s: float = spec(1.0, lo=0.0, hi=60.0, doc="sEMA width T for accelerations [s]")
    max_accel_mps2: float = spec(10.0, lo=0.1, hi=50.0, doc="|a| beyond this is an outlier [m/s^2]")
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
    cleaning: CleaningDataConfig = spec(CleaningDataConfig())


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
        build_table(StationPlaceConfig, p, f"data.stations.stations[{i}]", file)
        for i, p in enumerate(places)
    )
    if len({p.id for p in built}) != len(built):
        raise UserError(f"{file}: data.stations.stations places a station id twice")
    stations_cfg = dataclasses.replace(cfg.stations, stations=built)
    return dataclasses.replace(cfg, source=source, stations=stations_cfg)


@dataclass(frozen=True, kw_only=True)
class SectionScenario(ScenarioFile):
    """A scenario on a section of the user's SUMO network."""

    name: str = spec(doc="scenario name")
    seed: int = spec(0, lo=0, hi=2**32 - 1, doc="master seed for every random draw")
    network: SumoNetworkConfig = spec()
    section: SectionConfig = spec()
    instrumented: InstrumentedConfig = spec(InstrumentedConfig())
    simulation: SectionSimulationConfig = spec(SectionSimulationConfig())
    detectors: SectionDetectorConfig = spec(SectionDetectorConfig())
    bounds: SectionBoundsConfig = spec(SectionBoundsConfig())
    generator: SectionGeneratorConfig = spec(SectionGeneratorConfig())
    policy: PolicyConfig = spec(PolicyConfig())
    evaluation: EvaluationConfig = spec(EvaluationConfig())
    deploy: DeployConfig = spec(DeployConfig())
    data: DataConfig = spec(DataConfig())
    source: str = field(default="", compare=False)


def build_section_scenario(table: dict[str, Any], file: str, source: str) -> SectionScenario:
    """Validate a ``kind = "sumo"`` scenario table (raw TOML) into a ``SectionScenario``."""
    table = dict(table)
    data = build_data(table.pop("data", {}), file)
    sc = build_table(SectionScenario, table, "", file)
    sc = dataclasses.replace(sc, source=source, data=data)
    _check(sc, file)
    return sc


def _check(sc: SectionScenario, file: str) -> None:
    """Cross-field checks that no single range can express."""
    check_deploy(sc.deploy, file)
    _check_data(sc, file)
    net = sc.network
    if not net.sumocfg and not net.net_file:
        raise UserError(f"{file}: [network] needs sumocfg or net_file (kind = 'sumo')")
    for key in ("sumocfg", "net_file"):
        value = getattr(net, key)
        if value and not sc.resolve(value).is_file():
            raise UserError(f"{file}: network.{key} = {sc.resolve(value)} does not exist")
    for key in ("route_files", "additional_files"):
        for value in getattr(net, key):
            if not sc.resolve(value).is_file():
                raise UserError(f"{file}: network.{key} entry {sc.resolve(value)} does not exist")
    if not sc.section.edges:
        raise UserError(f"{file}: section.edges is empty; accepted: one or more edge IDs")
    if len(set(sc.section.edges)) != len(sc.section.edges):
        raise UserError(f"{file}: section.edges lists an edge twice")
    ins = sc.instrumented
    ways = [ins.vtype != "", bool(ins.ids)]
    if sum(ways) > 1:
        raise UserError(f"{file}: [instrumented] takes one of penetration, vtype or ids, not both")
    if not 0.0 < ins.penetration <= 1.0:
        raise UserError(
            f"{file}: instrumented.penetration = {ins.penetration!r} is out of range; "
            "accepted: (0, 1]"
        )
    a_min, a_max = sc.bounds.accel_mps2
    if not a_min < 0 < a_max:
        raise UserError(
            f"{file}: bounds.accel_mps2 = [{a_min:g}, {a_max:g}] must satisfy a_min < 0 < a_max"
        )
    if sc.evaluation.completions_per_scene != 1:
        raise UserError(
            f"{file}: evaluation.completions_per_scene = {sc.evaluation.completions_per_scene} "
            "is for ring scenarios; accepted 1 with [network] kind = 'sumo'"
        )
    if sc.detectors.interval_s > sc.simulation.duration_s:
        raise UserError(
            f"{file}: detectors.interval_s = {sc.detectors.interval_s:g} exceeds "
            f"simulation.duration_s = {sc.simulation.duration_s:g}; accepted <= duration"
        )
    if sc.simulation.duration_s < sc.detectors.interval_s * 2 and sc.simulation.n_runs < 2:
        raise UserError(
            f"{file}: one run with fewer than two detector intervals leaves nothing to hold out; "
            "accepted: simulation.n_runs >= 2 or duration_s >= 2 x detectors.interval_s"
        )


def _check_data(sc: SectionScenario, file: str) -> None:
    """A files source names its files (one per run, each there) and cannot ask for the true
    hidden count: only a simulation knows it."""
    data = sc.data
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
            if not sc.resolve(value).is_file():
                raise UserError(
                    f"{file}: data.{key}.files entry {sc.resolve(value)} does not exist"
                )
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
            if not sc.resolve(value).is_file():
                raise UserError(
                    f"{file}: data.stations.additional entry {sc.resolve(value)} does not exist"
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
    if sc.generator.k_source == "truth":
        raise UserError(
            f"{file}: generator.k_source = 'truth' needs a simulated ground truth; accepted "
            "'estimate' with data.source = 'files' (the hidden count of field data is unknown)"
        )

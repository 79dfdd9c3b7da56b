"""Scenarios on a user's own SUMO network: ``[network] kind = "sumo"`` plus a road section.

SUMO runs the user's network, demand and vehicle types (or the heterogeneous IDM fleet of
``[fleet]``: the paper's ring, ``scenario.ring_as_section``), and the method works on a
section of it: a list of connected edges in driving order (an open corridor) or a closed
loop. The tables use the typed-field machinery of ``scenario.fields``, so errors read the
same (file, key, accepted range).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.data import DataConfig, build_data, check_data
from macromicro_sumo.scenario.deploy_settings import DeployConfig, check_deploy
from macromicro_sumo.scenario.fields import ScenarioFile, build_table, spec
from macromicro_sumo.scenario.fleet import (
    FleetConfig,
    InitialConfig,
    SpeedLimitConfig,
    check_fleet_tables,
)
from macromicro_sumo.scenario.stages import EvaluationConfig, PolicyConfig, check_policy


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
    hidden: str = spec(
        "run",
        choices=("run", "snapshot"),
        doc="which vehicles Stages I and II and the evaluation treat as hidden: run = the "
        "non-instrumented ones, fixed per run (the default); snapshot = every recorded vehicle "
        "can be observed (a simulated truth records them all, e.g. the fleet) and each snapshot "
        "hides K of them at random, the ring's protocol: K drawn per snapshot from "
        "generator.hidden_train (the generator) or policy.hidden_train (Stage II's episodes), "
        "every snapshot at every K of generator.hidden_eval (evaluation, a per-K table); the "
        "instrumented vehicles still decide k_estimate.csv and who the deployment drives",
    )


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
    auto_boundary_stations: bool = spec(
        True,
        doc="with placed loops, also a station 15 m inside each open end and on both sides "
        "of every node where a ramp joins or leaves, so that the hidden count is counted "
        "(docs/sections.md, Hidden count)",
    )
    auto_occupancy_loop_m: float = spec(
        0.0,
        lo=0.0,
        hi=10.0,
        doc="with placed loops: beside each point loop a second E1 loop this long [m], ending "
        "at it, whose interval occupancy replaces the point loop's (a dual loop; counts and "
        "speeds stay the point loop's). 0: point loops only. A point loop near a stop line "
        "can sit in a gap of SUMO's standing queue and read a third of its density "
        "(docs/sections-log.md, stop 43); the user's own detectors are never changed",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )
    k_window_s: float = spec(
        60.0,
        lo=0.0,
        hi=1e6,
        doc="the hidden-count estimate averages detector density over this window [s]",
    )
    near_line_queue: bool | str = spec(
        False,
        choices=("all", "station"),
        accepted='true, false, "all" or "station"',
        doc="field data (data.source = files) with signals and point loops: true, where no "
        "station reads an approach's queue (its free-travel bound the largest), the hidden "
        "count adds the red's standing queue the loops within 25 m of the stop line miss "
        "(truth.standing; docs/sections-log.md, stop 47); all, every approach adds half of it; "
        "station, each near-line station the share its own loops missed (stop 49: K per lane "
        "on held-out arterials whose cars vary in length, free / congested, off 3.52 / 3.98, "
        "all 2.10 / 2.49, station 2.09 / 2.43; worse on SUMO truths of equal cars). Off: "
        "better on 12 of 37 arterials, worse on 565, 817, 818 and free-flowing 1304, 1309",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )


@dataclass(frozen=True, kw_only=True)
class SectionBoundsConfig:
    """Bounds that cannot be measured: actions and the safety gap."""

    accel_mps2: tuple[float, float] = spec(
        (-4.5, 2.6), lo=-50.0, hi=50.0, doc="action bounds [a_min, a_max] [m/s^2]"
    )
    min_gap_m: float = spec(2.0, lo=0.0, hi=100.0, doc="smallest admissible bumper gap [m]")
    psi_min_gap: str = spec(
        "bounds",
        choices=("bounds", "recorded"),
        doc="psi's smallest spacing (Stage I's placement bound) is the shortest recorded vType "
        "plus bounds: min_gap_m; recorded: the recorded vTypes' smallest minGap where the truth "
        "records one (1161, 615, Bremen: 2.5 m; generated pairs no longer start 2.0-2.5 m apart)",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )


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
    spacing_dispersion: str = spec(
        "measured",
        choices=("paper", "measured"),
        doc="L_var: paper = std of the spacings / mean (drives gaps equal); measured = their "
        "mean squared deviation from the mean spacing against the detectors' spacing variance "
        "(the paper's where the detectors give no spacing std)",
    )
    gap_choice: str = spec(
        "network",
        choices=("network", "posterior"),
        doc="which gap receives the next hidden vehicle: network = the generator's scores "
        "(the paper); posterior = drawn from the posterior of i.i.d. normal spacings with the "
        "detectors' mean and std (a closed one-lane section, spacing_dispersion = measured)",
    )
    eval_completions: int = spec(
        1,
        lo=1,
        hi=100,
        doc="completions of each held-out snapshot in the generator stage's metrics (the ring "
        "draws 4); generator_metrics.csv then has a completion column",
    )
    spacing_bounds: str = spec(
        "none",
        choices=("none", "passages"),
        doc="psi's largest spacing: none (no upper bound), or the longest of each detector "
        "interval's passage spacings widened per bounds_source (the ring's d_max): the loss's "
        "L_max and the placement keep the completed spacings under it",
    )
    dispersion_error: str = spec(
        "absolute",
        choices=("absolute", "squared"),
        doc="how the measured L_var compares a scene's spacing variance X with psi's: "
        "|X - sigma^2| / d^2 (absolute: the scenes' median X meets psi's) or "
        "(X - sigma^2)^2 / (d^2 sigma^2) (squared: their mean does)",
    )
    dispersion_feature: bool = spec(
        False,
        doc="each gap's features also say how much of psi's spacing variance the scene still "
        "lacks if the next vehicle halves that gap (the position head can then tell how far "
        "from the middle to go; docs/design.md, Ring as a section: status)",
    )
    spacing_set: str = spec(
        "all",
        choices=("all", "touched"),
        doc="the spacings A that the spacing terms score: every spacing of the completed "
        "scene (all), or only those with a generated vehicle at either end (touched, the "
        "ring's A)",
    )
    dispersion_center: str = spec(
        "psi",
        choices=("psi", "scene"),
        doc="the mean the measured dispersion counts deviations from: psi's mean spacing (the "
        "ring's), or on a closed section the completed scene's own, exact there (all its "
        "spacings around the loops); psi's on an open section",
    )
    bounds_source: str = spec(
        "margin",
        choices=("margin", "interval", "extended"),
        doc="psi's speed bounds from each detector interval's passages: their extremes widened "
        "by 10% (margin); as measured (interval); widened by (max - min) / (n - 1) on each "
        "side, n the interval's passages (extended, as the ring: n samples' extremes leave "
        "out ~2 / (n + 1) of the stream)",
    )
    hidden_layers: int = spec(
        1,
        lo=1,
        hi=2,
        doc="hidden ReLU layers of the generator's MLP (2: the ring generator's depth)",
    )
    dispersion_pool: float = spec(
        0.0,
        lo=0.0,
        hi=1e6,
        doc="weight of the pooled dispersion term: per hidden count, the scenes' summed spacing "
        "variance against psi's summed variance, added to L_var (0: off; "
        "generator/section_spread.py)",
    )
    lambda_pair: float = spec(
        0.0,
        lo=0.0,
        hi=1e6,
        doc="weight of L_pair: per hidden count, the pooled slope of leader speed - speed on "
        "spacing over the pairs a generated vehicle touches against the recorded vehicles' own "
        "pairs' (how the scene's spread moves once driven), plus the scenes' pooled speed "
        "variance against the detectors' (0: off, the paper; generator/pair_dynamics.py)",
    )
    ema_decay: float = spec(
        0.0,
        lo=0.0,
        hi=0.9999,
        doc="exponential moving average of the weights per batch, validated and kept instead "
        "of the raw weights (0: off, the paper)",
    )
    min_epochs: int = spec(
        0,
        lo=0,
        hi=100_000,
        doc="no early stop before this many epochs (patience counts on, but ends nothing)",
    )
    ema_warmup: bool = spec(
        False,
        doc="the moving average's decay ramps up as min(ema_decay, (1 + n) / (10 + n)) after n "
        "batches, so the early average does not hold on to the initial weights",
    )
    # The ring's keys, read only with instrumented.hidden = "snapshot" (data.section.hide).
    hidden_train: tuple[int, int] = spec(
        (0, 5),
        lo=0,
        hi=10_000,
        doc="K range in training with instrumented.hidden = snapshot, drawn per snapshot and "
        "epoch, at most the snapshot's vehicles [veh]",
    )
    hidden_eval: tuple[int, int] = spec(
        (1, 4),
        lo=0,
        hi=10_000,
        doc="K values in evaluation with instrumented.hidden = snapshot: every held-out "
        "snapshot with at least K vehicles at every K [veh]",
    )


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
    # The ring's demand source on a closed one-lane section (scenario/fleet.py); absent:
    # the user's route files are the demand.
    fleet: FleetConfig | None = spec(None, doc="the heterogeneous IDM fleet as the demand")
    speed_limits: SpeedLimitConfig | None = spec(None, doc="per-edge limits drawn per run")
    initial: InitialConfig | None = spec(None, doc="the fleet's initial state per run")
    source: str = field(default="", compare=False)


def build_section_scenario(table: dict[str, Any], file: str, source: str) -> SectionScenario:
    """Validate a ``kind = "sumo"`` scenario table (raw TOML) into a ``SectionScenario``."""
    table = dict(table)
    deploy = table.get("deploy", {})
    said = frozenset(deploy) if isinstance(deploy, dict) else None  # [deploy]'s keys set
    data = build_data(table.pop("data", {}), file)
    sc = build_table(SectionScenario, table, "", file)
    sc = dataclasses.replace(sc, source=source, data=data)
    sc = _resolved_reach(sc, said)
    _check(sc, file, said)
    return sc


def _resolved_reach(sc: SectionScenario, said: frozenset[str] | None) -> SectionScenario:
    """``deploy.merge_reach`` left at its default under ``deploy.merge`` "none" or
    "handover": "plain", what the driver does there (its occupation needs merge "sumo"), so
    that the scenario the run records says what runs; one the scenario sets stays as set,
    for ``check_deploy`` to refuse "occupation". "plain" is left out of the digest
    (``omit_value``): such a scenario keeps the digest it had before stop 46."""
    if said is None or "merge_reach" in said or sc.deploy.merge == "sumo":
        return sc
    return dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, merge_reach="plain"))


def _check(sc: SectionScenario, file: str, deploy_keys: frozenset[str] | None = None) -> None:
    """Cross-field checks that no single range can express; ``deploy_keys``: the [deploy]
    keys the scenario sets (``check_deploy``)."""
    # Field data's stations have their own interval: checked when the deployment is compared.
    sim, run_s = sc.data.source != "files", sc.simulation.warmup_s + sc.simulation.duration_s
    interval = sc.detectors.interval_s if sim else None
    check_deploy(sc.deploy, file, interval, run_s if sim else None, deploy_keys)
    check_policy(sc.policy, file)
    check_data(sc.data, sc.resolve, sc.generator.k_source, file)
    check_fleet_tables(sc, file)
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
    _check_hidden(sc, file)
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


def _check_hidden(sc: SectionScenario, file: str) -> None:
    """``instrumented.hidden = "snapshot"`` needs every vehicle recorded (a simulation) and
    the evaluation's K from 1 up (the typed pairs refuse a reversed range)."""
    if sc.instrumented.hidden != "snapshot":
        return
    if sc.data.source == "files":
        raise UserError(
            f'{file}: instrumented.hidden = "snapshot" hides recorded vehicles at random; field '
            'data records the instrumented ones only (data.source = "files"); accepted "run"'
        )
    if sc.generator.hidden_eval[0] < 1:
        raise UserError(
            f"{file}: generator.hidden_eval = {list(sc.generator.hidden_eval)} starts at 0; "
            "accepted K >= 1 (a scene with nothing hidden has nothing to evaluate)"
        )

"""The paper's ring scenario: an exact one-lane circle, its IDM fleet and the stage settings."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fields import Pair, ScenarioFile, spec
from macromicro_sumo.scenario.fleet import (
    FleetConfig,
    FleetDemand,
    InitialConfig,
    SpeedLimitConfig,
    check_fleet,
)
from macromicro_sumo.scenario.stages import (
    DeployConfig,
    EvaluationConfig,
    PolicyConfig,
    check_deploy,
)


@dataclass(frozen=True, kw_only=True)
class NetworkConfig:
    """The ring road: an exact single-lane circle split into edges (piecewise limits)."""

    radius_m: float = spec(lo=1.0, hi=100_000.0, doc="ring radius R [m]")
    n_edges: int = spec(4, lo=1, hi=64, doc="edges the ring is split into (speed-limit pieces)")
    net_file: str = spec(doc="SUMO .net.xml, relative to the scenario file")
    routes_file: str = spec(doc="additional file with one-lap routes and rerouters")

    @property
    def length_m(self) -> float:
        """Ring length L = 2 pi R [m]."""
        return 2.0 * math.pi * self.radius_m


@dataclass(frozen=True, kw_only=True)
class SimulationConfig:
    """How SUMO runs the ground truth."""

    step_length_s: float = spec(0.5, lo=0.01, hi=5.0, doc="SUMO step length = policy step dt [s]")
    duration_s: float = spec(lo=1.0, hi=1e6, doc="recorded duration of each run [s]")
    n_runs: int = spec(lo=1, hi=100_000, doc="independent ground-truth runs")


@dataclass(frozen=True, kw_only=True)
class DetectorConfig:
    """Loop detectors on every edge: E1 at mid-edge, E2 over the edge, instant loops."""

    interval_s: float = spec(60.0, lo=1.0, hi=1e6, doc="aggregation interval [s]")
    e1_position: float = spec(
        0.5, lo=0.0, hi=1.0, doc="E1/instant loop position as a fraction of edge"
    )


@dataclass(frozen=True, kw_only=True)
class BoundsConfig:
    """The paper's fixed bounds (case-study table)."""

    speed_mps: Pair = spec(lo=0.0, hi=100.0, doc="admissible speeds [v_min, v_max] [m/s]")
    spacing_m: Pair = spec(lo=0.0, hi=1e6, doc="admissible spacings [d_min, d_max] [m]")
    accel_mps2: Pair = spec(lo=-50.0, hi=50.0, doc="action bounds [a_min, a_max] [m/s^2]")


@dataclass(frozen=True, kw_only=True)
class GeneratorConfig:
    """Stage I: hidden-vehicle generator."""

    hidden_train: tuple[int, int] = spec((0, 5), lo=0, hi=10_000, doc="K range in training [veh]")
    hidden_eval: tuple[int, int] = spec((1, 4), lo=0, hi=10_000, doc="K range in evaluation [veh]")
    t_max: int = spec(20, lo=1, hi=10_000, doc="max trials per hidden vehicle T_max")
    lambda_v: float = spec(0.5, lo=0.0, hi=1e6, doc="speed penalty weight lambda_v")
    lambda_d: float = spec(0.5, lo=0.0, hi=1e6, doc="spacing penalty weight lambda_d")
    lambda_rec: float = spec(
        0.0, lo=0.0, hi=1e6, doc="reconstruction weight (0: off, as the paper)"
    )
    psi_source: str = spec("detectors", choices=("detectors", "trajectories"), doc="Psi source")
    spacing_dispersion: str = spec(
        "paper",
        choices=("paper", "measured"),
        doc="L_var: paper = std of the touched gaps / mean (drives gaps equal); measured = their "
        "mean squared deviation from the mean spacing against the detectors' spacing variance",
    )
    gap_choice: str = spec(
        "network",
        choices=("network", "posterior"),
        doc="which gap receives the next hidden vehicle: network = the generator's scores "
        "(the paper); posterior = drawn from the posterior of i.i.d. normal spacings with the "
        "detectors' mean and std (needs spacing_dispersion = measured)",
    )
    bounds_source: str = spec(
        "interval",
        choices=("interval", "extended", "fixed"),
        doc="Psi bounds: measured per interval; the same widened by (max - min) / (n - 1) on "
        "each side, n the interval's samples (n samples' extremes leave out ~2 / (n + 1) of "
        "the stream); or fixed",
    )
    snapshot_every_s: float = spec(5.0, lo=0.01, hi=1e6, doc="time between snapshots [s]")
    held_out_fraction: float = spec(0.25, lo=0.01, hi=0.99, doc="share of runs held out")
    hidden_size: int = spec(64, lo=4, hi=4096, doc="MLP width")
    epochs: int = spec(60, lo=1, hi=100_000, doc="max training epochs")
    batch_size: int = spec(256, lo=1, hi=1_000_000, doc="snapshots per batch")
    lr: float = spec(3e-3, lo=1e-7, hi=1.0, doc="Adam learning rate")
    patience: int = spec(10, lo=1, hi=100_000, doc="early-stopping patience [epochs]")
    ema_decay: float = spec(
        0.0,
        lo=0.0,
        hi=0.9999,
        doc="exponential moving average of the weights per batch, validated and kept instead "
        "of the raw weights (0: off, the paper)",
    )


@dataclass(frozen=True, kw_only=True)
class Scenario(ScenarioFile):
    """A whole scenario file. ``source`` is the file it came from (for messages and paths)."""

    name: str = spec(doc="scenario name")
    seed: int = spec(0, lo=0, hi=2**32 - 1, doc="master seed for every random draw")
    network: NetworkConfig = spec()
    fleet: FleetConfig = spec()
    speed_limits: SpeedLimitConfig = spec()
    initial: InitialConfig = spec()
    simulation: SimulationConfig = spec()
    detectors: DetectorConfig = spec(DetectorConfig())
    bounds: BoundsConfig = spec()
    generator: GeneratorConfig = spec(GeneratorConfig())
    policy: PolicyConfig = spec(PolicyConfig())
    evaluation: EvaluationConfig = spec(EvaluationConfig())
    deploy: DeployConfig = spec(DeployConfig())
    source: str = field(default="", compare=False)

    @property
    def fleet_demand(self) -> FleetDemand:
        """The fleet, its speed limits and initial state: the ring's demand source."""
        return FleetDemand(self.fleet, self.speed_limits, self.initial)


def check_consistency(sc: Scenario, file: str) -> None:
    """Cross-field checks that no single range can express."""
    check_deploy(sc.deploy, file)
    if sc.deploy.vtype:
        raise UserError(
            f"{file}: deploy.vtype = {sc.deploy.vtype!r} is for section scenarios; on the ring "
            "every vehicle has its own vType: accepted '' (use deploy.share)"
        )
    if sc.policy.driver_speed != "none":  # the ring wing's env knows none: say so, not ignore it
        raise UserError(
            f'{file}: policy.driver_speed = "{sc.policy.driver_speed}" is for section scenarios '
            '(road = "section" runs this ring as one); accepted "none"'
        )
    length = sc.network.length_m
    n = sc.fleet.n_vehicles
    d_min, d_max = sc.bounds.spacing_m
    if d_min * n > length:
        raise UserError(
            f"{file}: bounds.spacing_m = [{d_min:g}, {d_max:g}] cannot be met: {n} vehicles x "
            f"d_min = {d_min * n:.2f} m > ring length {length:.2f} m; accepted d_min <= {length / n:.2f}"
        )
    if d_max * n < length:
        raise UserError(
            f"{file}: bounds.spacing_m = [{d_min:g}, {d_max:g}] cannot be met: {n} vehicles x "
            f"d_max = {d_max * n:.2f} m < ring length {length:.2f} m; accepted d_max >= {length / n:.2f}"
        )
    a_min, a_max = sc.bounds.accel_mps2
    if not a_min < 0 < a_max:
        raise UserError(
            f"{file}: bounds.accel_mps2 = [{a_min:g}, {a_max:g}] must satisfy a_min < 0 < a_max"
        )
    check_fleet(sc.fleet_demand, length, "ring", file)
    for name in ("hidden_train", "hidden_eval"):
        lo, hi = getattr(sc.generator, name)
        if hi > n:
            raise UserError(
                f"{file}: generator.{name} = [{lo}, {hi}] exceeds N = {n}; accepted [0, {n}]"
            )
    if sc.generator.gap_choice == "posterior" and sc.generator.spacing_dispersion != "measured":
        raise UserError(
            f'{file}: generator.gap_choice = "posterior" needs the detectors\' spacing std: '
            f'generator.spacing_dispersion = "{sc.generator.spacing_dispersion}"; accepted "measured"'
        )
    if sc.simulation.duration_s < sc.simulation.step_length_s * 2:
        raise UserError(f"{file}: simulation.duration_s must cover at least two steps")
    if sc.detectors.interval_s > sc.simulation.duration_s:
        raise UserError(
            f"{file}: detectors.interval_s = {sc.detectors.interval_s:g} exceeds simulation.duration_s "
            f"= {sc.simulation.duration_s:g}; accepted <= duration"
        )

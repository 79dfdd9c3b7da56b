"""Typed scenario configuration, loaded from TOML and validated field by field.

A scenario file has one table per dataclass below. Every field has a unit in its name
or docstring (``metadata["doc"]``) and, where it makes sense, an accepted range
(``metadata["range"]``, inclusive; ``None`` means unbounded). Loading rejects unknown
keys, missing required keys, wrong types and out-of-range values with a one-line
``UserError`` that names the file, the key and the accepted range.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from macromicro_sumo.errors import UserError

Pair = tuple[float, float]


def _f(
    default: Any = dataclasses.MISSING,
    *,
    lo: float | None = None,
    hi: float | None = None,
    doc: str = "",
    choices: tuple[str, ...] | None = None,
) -> Any:
    meta = {"range": (lo, hi), "doc": doc, "choices": choices}
    if default is dataclasses.MISSING:
        return field(metadata=meta)
    if isinstance(default, list | dict):
        return field(default_factory=lambda d=default: type(d)(d), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True, kw_only=True)
class NetworkConfig:
    """The ring road: an exact single-lane circle split into edges (piecewise limits)."""

    radius_m: float = _f(lo=1.0, hi=100_000.0, doc="ring radius R [m]")
    n_edges: int = _f(4, lo=1, hi=64, doc="edges the ring is split into (speed-limit pieces)")
    net_file: str = _f(doc="SUMO .net.xml, relative to the scenario file")
    routes_file: str = _f(doc="additional file with one-lap routes and rerouters")

    @property
    def length_m(self) -> float:
        """Ring length L = 2 pi R [m]."""
        return 2.0 * math.pi * self.radius_m


@dataclass(frozen=True, kw_only=True)
class FleetConfig:
    """Heterogeneous IDM drivers: each vehicle draws its own parameters from these ranges."""

    n_vehicles: int = _f(lo=2, hi=10_000, doc="vehicles on the ring N")
    length_m: float = _f(5.0, lo=0.5, hi=30.0, doc="vehicle length [m]")
    accel_mps2: Pair = _f(lo=0.01, hi=10.0, doc="IDM maximum acceleration a range [m/s^2]")
    decel_mps2: Pair = _f(lo=0.01, hi=10.0, doc="IDM comfortable deceleration b range [m/s^2]")
    tau_s: Pair = _f(lo=0.1, hi=10.0, doc="IDM desired time headway T range [s]")
    min_gap_m: Pair = _f(lo=0.0, hi=50.0, doc="IDM jam distance s0 range [m]")
    delta: float = _f(4.0, lo=1.0, hi=10.0, doc="IDM acceleration exponent (same for all)")
    speed_factor: Pair = _f(lo=0.1, hi=3.0, doc="desired speed / local limit range [-]")
    max_speed_mps: Pair = _f((50.0, 50.0), lo=0.1, hi=100.0, doc="vehicle top speed range [m/s]")


@dataclass(frozen=True, kw_only=True)
class SpeedLimitConfig:
    """Random piecewise-constant limits: each edge draws its own limit per run."""

    range_mps: Pair = _f(lo=0.1, hi=100.0, doc="per-edge limit range [m/s]")
    step_mps: float = _f(
        0.5, lo=0.0, hi=10.0, doc="limits are rounded to this step [m/s] (0: none)"
    )


@dataclass(frozen=True, kw_only=True)
class InitialConfig:
    """Initial conditions away from steady state."""

    speed_mps: Pair = _f(lo=0.0, hi=100.0, doc="initial speeds, uniform in this range [m/s]")
    spacing_concentration: float = _f(
        20.0, lo=0.1, hi=1e6, doc="Dirichlet concentration of initial spacings (high: even)"
    )
    min_spacing_m: float = _f(
        20.0, lo=0.0, hi=1e5, doc="smallest initial front-to-front spacing [m]"
    )


@dataclass(frozen=True, kw_only=True)
class SimulationConfig:
    """How SUMO runs the ground truth."""

    step_length_s: float = _f(0.5, lo=0.01, hi=5.0, doc="SUMO step length = policy step dt [s]")
    duration_s: float = _f(lo=1.0, hi=1e6, doc="recorded duration of each run [s]")
    n_runs: int = _f(lo=1, hi=100_000, doc="independent ground-truth runs")


@dataclass(frozen=True, kw_only=True)
class DetectorConfig:
    """Loop detectors on every edge: E1 at mid-edge, E2 over the edge, instant loops."""

    interval_s: float = _f(60.0, lo=1.0, hi=1e6, doc="aggregation interval [s]")
    e1_position: float = _f(
        0.5, lo=0.0, hi=1.0, doc="E1/instant loop position as a fraction of edge"
    )


@dataclass(frozen=True, kw_only=True)
class BoundsConfig:
    """The paper's fixed bounds (case-study table)."""

    speed_mps: Pair = _f(lo=0.0, hi=100.0, doc="admissible speeds [v_min, v_max] [m/s]")
    spacing_m: Pair = _f(lo=0.0, hi=1e6, doc="admissible spacings [d_min, d_max] [m]")
    accel_mps2: Pair = _f(lo=-50.0, hi=50.0, doc="action bounds [a_min, a_max] [m/s^2]")


@dataclass(frozen=True, kw_only=True)
class GeneratorConfig:
    """Stage I: hidden-vehicle generator."""

    hidden_train: tuple[int, int] = _f((0, 5), lo=0, hi=10_000, doc="K range in training [veh]")
    hidden_eval: tuple[int, int] = _f((1, 4), lo=0, hi=10_000, doc="K range in evaluation [veh]")
    t_max: int = _f(20, lo=1, hi=10_000, doc="max trials per hidden vehicle T_max")
    lambda_v: float = _f(0.5, lo=0.0, hi=1e6, doc="speed penalty weight lambda_v")
    lambda_d: float = _f(0.5, lo=0.0, hi=1e6, doc="spacing penalty weight lambda_d")
    lambda_rec: float = _f(0.0, lo=0.0, hi=1e6, doc="reconstruction weight (0: off, as the paper)")
    psi_source: str = _f("detectors", choices=("detectors", "trajectories"), doc="Psi source")
    spacing_dispersion: str = _f(
        "paper",
        choices=("paper", "measured"),
        doc="L_var: paper = std of the touched gaps / mean (drives gaps equal); measured = their "
        "mean squared deviation from the mean spacing against the detectors' spacing variance",
    )
    gap_choice: str = _f(
        "network",
        choices=("network", "posterior"),
        doc="which gap receives the next hidden vehicle: network = the generator's scores "
        "(the paper); posterior = drawn from the posterior of i.i.d. normal spacings with the "
        "detectors' mean and std (needs spacing_dispersion = measured)",
    )
    bounds_source: str = _f(
        "interval",
        choices=("interval", "extended", "fixed"),
        doc="Psi bounds: measured per interval; the same widened by (max - min) / (n - 1) on "
        "each side, n the interval's samples (n samples' extremes leave out ~2 / (n + 1) of "
        "the stream); or fixed",
    )
    snapshot_every_s: float = _f(5.0, lo=0.01, hi=1e6, doc="time between snapshots [s]")
    held_out_fraction: float = _f(0.25, lo=0.01, hi=0.99, doc="share of runs held out")
    hidden_size: int = _f(64, lo=4, hi=4096, doc="MLP width")
    epochs: int = _f(60, lo=1, hi=100_000, doc="max training epochs")
    batch_size: int = _f(256, lo=1, hi=1_000_000, doc="snapshots per batch")
    lr: float = _f(3e-3, lo=1e-7, hi=1.0, doc="Adam learning rate")
    patience: int = _f(10, lo=1, hi=100_000, doc="early-stopping patience [epochs]")
    ema_decay: float = _f(
        0.0,
        lo=0.0,
        hi=0.9999,
        doc="exponential moving average of the weights per batch, validated and kept instead "
        "of the raw weights (0: off, the paper)",
    )


@dataclass(frozen=True, kw_only=True)
class PolicyConfig:
    """Stage II: shared policy trained with PPO on micro + eta * macro."""

    eta: float = _f(0.3, lo=0.0, hi=1e6, doc="macro reward weight eta")
    horizon: int = _f(10, lo=1, hi=100_000, doc="episode length H [policy steps]")
    objective: str = _f("mix", choices=("mix", "micro_only", "macro_only"), doc="ablation switch")
    observation: str = _f(
        "paper",
        choices=("paper", "lookahead"),
        doc="paper: [v, v_limit, spacing, delta_v]; lookahead adds [next edge's limit, distance to it]",
    )
    hidden_train: tuple[int, int] = _f((1, 4), lo=1, hi=10_000, doc="K range of training episodes")
    updates: int = _f(60, lo=1, hi=1_000_000, doc="PPO updates")
    episodes_per_update: int = _f(32, lo=1, hi=100_000, doc="episodes per rollout")
    epochs: int = _f(4, lo=1, hi=1000, doc="PPO epochs per update")
    minibatches: int = _f(4, lo=1, hi=1000, doc="minibatches per epoch")
    lr: float = _f(3e-3, lo=1e-7, hi=1.0, doc="Adam learning rate")
    gamma: float = _f(0.99, lo=0.0, hi=1.0, doc="discount")
    gae_lambda: float = _f(0.95, lo=0.0, hi=1.0, doc="GAE lambda")
    clip_coef: float = _f(0.2, lo=0.0, hi=10.0, doc="PPO clip")
    vf_coef: float = _f(0.5, lo=0.0, hi=100.0, doc="value loss weight")
    ent_coef: float = _f(0.0, lo=0.0, hi=10.0, doc="entropy bonus weight")
    hidden_size: int = _f(64, lo=4, hi=4096, doc="MLP width")
    init_log_std: float = _f(
        -1.0, lo=-10.0, hi=2.0, doc="initial log std of the action [log m/s^2]"
    )
    lr_schedule: str = _f(
        "constant",
        choices=("constant", "linear"),
        doc="Adam rate over the updates: constant, or linear decay to 0 after the last update "
        "(the final policy is then not one noisy step of a constant rate)",
    )
    micro_pairs: str = _f(
        "all",
        choices=("all", "observed_leader"),
        doc="observed vehicle-steps in r_micro: all (the paper), or only those whose leader is "
        "observed too (behind a hidden leader the spacing and delta_v are generated, not the "
        "ones the recorded action answered)",
    )
    micro_replay: int = _f(
        1,
        lo=1,
        hi=1_000_000,
        doc="rollouts whose observed pairs r_micro uses at each update (1: this update's only, "
        "the paper); with observed_leader the pairs do not depend on the policy",
    )
    macro_speed_scale_mps: float = _f(
        0.0,
        lo=0.0,
        hi=1e3,
        doc="r_macro's L_speed: 0 is the paper's (v / v_mean - 1)^2; s > 0 makes it "
        "((v - v_mean) / s)^2, a bias of s costing as much as the paper's 100% error",
    )
    checkpoint_selection: str = _f(
        "last",
        choices=("last", "val_micro_logp"),
        doc="policy kept: the last update's, or the update's with the best micro log-likelihood "
        "on the validation runs (their episodes are then not trained on)",
    )
    checkpoint_every: int = _f(5, lo=1, hi=1_000_000, doc="updates between resumable checkpoints")
    refine_iterations: int = _f(
        0,
        lo=0,
        hi=100,
        doc="joint refinement: outer iterations of Algorithm 1 (0: single pass, the paper's case study)",
    )
    refine_updates: int = _f(20, lo=1, hi=1_000_000, doc="PPO updates per refinement iteration")
    refine_epochs: int = _f(20, lo=1, hi=100_000, doc="generator epochs per refinement iteration")
    refine_lambda_rec: float = _f(
        1.0,
        lo=0.0,
        hi=1e6,
        doc="weight of the consistency term L_rec against policy-rolled hidden states",
    )


@dataclass(frozen=True, kw_only=True)
class EvaluationConfig:
    """Evaluation protocol: macro alignment rollouts and leader-follower tests."""

    horizon_steps: int = _f(10, lo=1, hi=100_000, doc="rollout length for macro alignment [steps]")
    completions_per_scene: int = _f(
        1,
        lo=1,
        hi=1_000,
        doc="independent generator completions of each held-out scene, each rolled out by every "
        "method (ring scenarios): each completion is one random draw, so more of them shrink "
        "the evaluation's noise",
    )
    lf_trials: int = _f(20, lo=1, hi=100_000, doc="stochastic leader-follower trials per method")
    lf_duration_s: float = _f(60.0, lo=1.0, hi=1e5, doc="leader-follower test length [s]")
    min_safe_gap_m: float = _f(
        2.0, lo=0.0, hi=1e3, doc="minimum safe bumper gap in leader-follower tests [m]"
    )
    fcd_episodes: int = _f(
        20, lo=0, hi=100_000, doc="episodes per method and K written as SUMO FCD"
    )
    timespace_s: float = _f(
        120.0, lo=1.0, hi=1e5, doc="length of the time-space diagram rollouts [s]"
    )


class ScenarioFile:
    """What every scenario kind does with the file it came from (``source``)."""

    source: str

    def resolve(self, relative: str) -> Path:
        """A path from the scenario file, relative to the file's folder."""
        p = Path(relative)
        return p if p.is_absolute() else (Path(self.source).parent / p).resolve()

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d.pop("source")
        return d

    def digest(self) -> str:
        """SHA-256 of the scenario as loaded (not of the file's bytes or comments)."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True, kw_only=True)
class Scenario(ScenarioFile):
    """A whole scenario file. ``source`` is the file it came from (for messages and paths)."""

    name: str = _f(doc="scenario name")
    seed: int = _f(0, lo=0, hi=2**32 - 1, doc="master seed for every random draw")
    network: NetworkConfig = _f()
    fleet: FleetConfig = _f()
    speed_limits: SpeedLimitConfig = _f()
    initial: InitialConfig = _f()
    simulation: SimulationConfig = _f()
    detectors: DetectorConfig = _f(DetectorConfig())
    bounds: BoundsConfig = _f()
    generator: GeneratorConfig = _f(GeneratorConfig())
    policy: PolicyConfig = _f(PolicyConfig())
    evaluation: EvaluationConfig = _f(EvaluationConfig())
    source: str = field(default="", compare=False)


# --------------------------------------------------------------------------- loading


def _describe_range(meta: dict[str, Any]) -> str:
    lo, hi = meta.get("range", (None, None))
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    return f"[{lo_s}, {hi_s}]"


def _check_scalar(value: Any, kind: type, key: str, meta: dict[str, Any], file: str) -> Any:
    accepted = _describe_range(meta)
    if kind is bool:
        if not isinstance(value, bool):
            raise UserError(f"{file}: {key} = {value!r} must be true or false")
        return value
    if kind is str:
        if not isinstance(value, str):
            raise UserError(f"{file}: {key} = {value!r} must be a string")
        choices = meta.get("choices")
        if choices and value not in choices:
            raise UserError(f"{file}: {key} = {value!r} is not accepted; accepted: {accepted}")
        return value
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise UserError(f"{file}: {key} = {value!r} must be a number in {accepted}")
    if kind is int and not float(value).is_integer():
        raise UserError(f"{file}: {key} = {value!r} must be an integer in {accepted}")
    value = kind(value)
    if not math.isfinite(value):
        raise UserError(f"{file}: {key} = {value!r} must be finite, in {accepted}")
    lo, hi = meta.get("range", (None, None))
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise UserError(f"{file}: {key} = {value!r} is out of range; accepted: {accepted}")
    return value


def _build(cls: type, table: Any, prefix: str, file: str) -> Any:
    if not isinstance(table, dict):
        raise UserError(f"{file}: [{prefix}] must be a table")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls) if f.name != "source"}
    for key in table:
        if key not in known:
            where = f"[{prefix}] " if prefix else ""
            raise UserError(
                f"{file}: unknown key {where}{key!r}; accepted keys: {', '.join(sorted(known))}"
            )
    kwargs: dict[str, Any] = {}
    for name, f in known.items():
        key = f"{prefix}.{name}" if prefix else name
        if name not in table:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                hint = hints[name]
                what = f"table [{key}]" if dataclasses.is_dataclass(hint) else f"key {key!r}"
                raise UserError(f"{file}: missing required {what}")
            continue
        hint = hints[name]
        value = table[name]
        if dataclasses.is_dataclass(hint):
            kwargs[name] = _build(hint, value, key, file)
        elif typing.get_origin(hint) is list:
            kind = typing.get_args(hint)[0]
            if not isinstance(value, list):
                raise UserError(f"{file}: {key} = {value!r} must be a list")
            kwargs[name] = [_check_scalar(v, kind, key, f.metadata, file) for v in value]
        elif typing.get_origin(hint) is tuple:
            kind = typing.get_args(hint)[0]
            if not isinstance(value, list) or len(value) != 2:
                raise UserError(
                    f"{file}: {key} = {value!r} must be a pair [low, high] in {_describe_range(f.metadata)}"
                )
            pair = tuple(_check_scalar(v, kind, key, f.metadata, file) for v in value)
            if pair[0] > pair[1]:
                raise UserError(
                    f"{file}: {key} = {value!r} is reversed; accepted [low, high] with "
                    f"low <= high, both in {_describe_range(f.metadata)}"
                )
            kwargs[name] = pair
        else:
            kind = hint if isinstance(hint, type) else typing.get_args(hint)[0]
            if isinstance(hint, types.UnionType):
                kind = typing.get_args(hint)[0]
            kwargs[name] = _check_scalar(value, kind, key, f.metadata, file)
    return cls(**kwargs)


def _check_consistency(sc: Scenario, file: str) -> None:
    """Cross-field checks that no single range can express."""
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
    if n * sc.fleet.length_m >= length:
        raise UserError(
            f"{file}: fleet of {n} x {sc.fleet.length_m:g} m does not fit on a {length:.2f} m ring"
        )
    if n * sc.initial.min_spacing_m >= length:
        raise UserError(
            f"{file}: initial.min_spacing_m = {sc.initial.min_spacing_m:g} too large for {n} vehicles; "
            f"accepted < {length / n:.2f}"
        )
    if sc.initial.min_spacing_m < sc.fleet.length_m:
        raise UserError(
            f"{file}: initial.min_spacing_m = {sc.initial.min_spacing_m:g} < vehicle length "
            f"{sc.fleet.length_m:g}; accepted >= {sc.fleet.length_m:g}"
        )
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


def read_scenario_toml(path: str | Path) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The raw tables of a scenario file: (scenario table, its ``[sweep]`` table or None)."""
    path = Path(path)
    file = str(path)
    if not path.is_file():
        raise UserError(f"{file}: scenario file not found")
    try:
        table = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{file}: malformed TOML ({exc})") from None
    except UnicodeDecodeError:
        raise UserError(f"{file}: not a text file (malformed TOML)") from None
    return table, table.pop("sweep", None)


def load_scenario(
    path: str | Path, overrides: dict[str, Any] | None = None, *, allow_sweep: bool = False
) -> Any:
    """Load and validate a scenario TOML; ``overrides`` maps dotted keys to values (sweeps).

    A ``[sweep]`` table is for ``macromicro batch``, which passes ``allow_sweep=True`` and
    one variant's values as ``overrides``; elsewhere it is an error.
    """
    path = Path(path)
    file = str(path)
    table, sweep = read_scenario_toml(path)
    if sweep is not None and not allow_sweep:
        raise UserError(
            f"{file}: has a [sweep] table; run its variants with `macromicro batch {file}`"
        )
    for dotted, value in (overrides or {}).items():
        node = table
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    network = table.get("network")
    kind = network.get("kind", "ring") if isinstance(network, dict) else "ring"
    if kind == "sumo":
        from macromicro_sumo.section_config import build_section_scenario

        return build_section_scenario(table, file, str(path.resolve()))
    if kind != "ring":
        raise UserError(
            f"{file}: network.kind = {kind!r} is not accepted; accepted: one of 'ring', 'sumo'"
        )
    network.pop("kind", None)
    sc = _build(Scenario, table, "", file)
    sc = dataclasses.replace(sc, source=str(path.resolve()))
    _check_consistency(sc, file)
    for key in ("net_file", "routes_file"):
        p = sc.resolve(getattr(sc.network, key))
        if not p.is_file():
            raise UserError(f"{file}: network.{key} = {p} does not exist")
    return sc


def scenario_from_dict(d: dict[str, Any], source: str) -> Any:
    """Rebuild a scenario stored in a checkpoint or manifest (already validated once)."""
    if d.get("network", {}).get("kind") == "sumo":
        from macromicro_sumo.section_config import SectionScenario

        return dataclasses.replace(_build(SectionScenario, d, "", source), source=source)
    return dataclasses.replace(_build(Scenario, d, "", source), source=source)

"""Shared fixtures: small copies of the paper's ring scenario, written into tmp folders."""

from __future__ import annotations

import json
import re
import subprocess
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
import sumo
import sumolib
import torch

from macromicro_sumo.cli import main
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.pipeline import parallel
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.road.section import Section, read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.netgen import random_corridor
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[1]
PAPER_SCENARIO = ROOT / "scenarios" / "ring_paper.toml"
NETS = ROOT / "sumo_nets"

# Small enough that a whole simulate stage takes a fraction of a second.
SMALL = {"simulation.n_runs": 2, "simulation.duration_s": 120.0}

MakeScenario = Callable[..., Path]

# game/cross's fitted Krauss prior (hU's run at stop 34, policy/policy_manifest.json).
CROSS_KRAUSS = {
    "speed_factor": 1.0327,
    "accel_mps2": 2.6,
    "decel_mps2": 5.629,
    "tau_s": 1.0896,
    "min_gap_m": 2.4947,
    "veh_length_m": 5.0,
    "dt_s": 0.5,
    "relax_s": 0.5545,
}


@pytest.fixture
def cross_krauss() -> dict[str, float]:
    """``CROSS_KRAUSS``, a copy for one test to change."""
    return dict(CROSS_KRAUSS)


def prior_alone(params: dict[str, float], prior: str = "krauss") -> Callable:
    """The deployment's action batch (``deploy.stage.policy_batch``) of a ``prior`` with
    ``params`` alone: residual 0, the "lookahead" observation."""
    agent = Agent(
        observation="lookahead", prior=prior, prior_params=params, residual_bound_mps2=0.0
    )
    return policy_batch(agent)


def one_phase_program(folder: Path, tls: str, state: str, name: str = "red") -> Path:
    """``folder / f"{name}.add.xml"``: signal ``tls``'s program ``name``, one phase of
    ``state`` that lasts the whole run."""
    path = folder / f"{name}.add.xml"
    path.write_text(
        f'<additional>\n    <tlLogic id="{tls}" type="static" programID="{name}" offset="0">\n'
        f'        <phase duration="10000" state="{state}"/>\n    </tlLogic>\n</additional>\n'
    )
    return path


def small_section_scenario(
    folder: Path, net: Path, routes: Path, edges: list[str], additional: tuple[Path, ...] = (),
    **tables: Any,
) -> SectionScenario:  # fmt: skip
    """``section_files.section_scenario`` loaded, written to ``folder / "s.toml"``: seed 5,
    two runs of 60 s without warm-up, 30 s detector intervals, 10% instrumented (the
    default), the "lookahead" observation, the ``additional`` files; ``tables``: top-level
    tables added or replaced (``simulation``, ``instrumented``, ...)."""
    from section_files import section_scenario  # it imports this module

    if additional:
        network = {"kind": "sumo", "net_file": str(net), "route_files": [str(routes)]}
        tables = {"network": {**network, "additional_files": list(map(str, additional))}, **tables}
    tables = {
        "simulation": {"warmup_s": 0.0, "duration_s": 60.0, "n_runs": 2},
        "detectors": {"interval_s": 30.0},
        "policy": {"observation": "lookahead"},
        **tables,
    }
    path = section_scenario(
        folder / "s.toml", net, routes, edges, seed=5, penetration=0.1, **tables
    )
    return load_scenario(path)


def cross_program(folder: Path, green: tuple[int, ...] = ()) -> Path:
    """game/cross's signal "0" red on every link but ``green`` (link indices) all along
    (``one_phase_program``)."""
    return one_phase_program(folder, "0", "".join("G" if k in green else "r" for k in range(12)))


def stop_offset_net(folder: Path) -> Path:
    """A (300 m, 2 lanes; stopOffset 3 m, lane 1's own 6 m for passenger cars) -> a light
    "tl" -> B (200 m, 2 lanes), built by netconvert."""
    nodes = (
        '<node id="n0" x="0" y="0"/><node id="tl" x="300" y="0" type="traffic_light"/>'
        '<node id="n2" x="500" y="0"/>'
    )
    edges = (
        '<edge id="A" from="n0" to="tl" numLanes="2" speed="15"><stopOffset value="3"/>'
        '<lane index="1"><stopOffset value="6" vClasses="passenger"/></lane></edge>'
        '<edge id="B" from="tl" to="n2" numLanes="2" speed="15"/>'
    )
    return netconvert(folder, nodes, edges)


def netconvert(
    folder: Path, nodes: str, edges: str, cons: str = "", extra: tuple = (), name: str = "net"
) -> Path:
    """``folder / f"{name}.net.xml"``, built by netconvert from the elements inside
    ``<nodes>``, ``<edges>`` and (where given) ``<connections>``; ``extra``: more options."""
    (folder / f"{name}.nod.xml").write_text(f"<nodes>\n{nodes}\n</nodes>\n")
    (folder / f"{name}.edg.xml").write_text(f"<edges>\n{edges}\n</edges>\n")
    cmd = [
        sumolib.checkBinary("netconvert"),
        "--node-files", str(folder / f"{name}.nod.xml"),
        "--edge-files", str(folder / f"{name}.edg.xml"),
        "--output-file", str(folder / f"{name}.net.xml"),
        "--no-turnarounds", "true",
        "--no-warnings", "true",
        *extra,
    ]  # fmt: skip
    if cons:
        (folder / f"{name}.con.xml").write_text(f"<connections>\n{cons}\n</connections>\n")
        cmd += ["--connection-files", str(folder / f"{name}.con.xml")]
    subprocess.run(cmd, check=True, capture_output=True)
    return folder / f"{name}.net.xml"


def light_road(folder: Path, a_m: float, b_m: float, speed_mps: float) -> Path:
    """One lane A (``a_m``) -> a traffic light "tl" -> B (``b_m``), both at ``speed_mps``:
    the net file (the light's program is the test's own additional file)."""
    folder.mkdir(parents=True, exist_ok=True)
    x_b = a_m + b_m
    nodes = (
        f'<node id="n0" x="0" y="0"/>\n<node id="tl" x="{a_m:g}" y="0" type="traffic_light"/>\n'
        f'<node id="n2" x="{x_b:g}" y="0"/>'
    )
    edges = (
        f'<edge id="A" from="n0" to="tl" numLanes="1" speed="{speed_mps:g}"/>\n'
        f'<edge id="B" from="tl" to="n2" numLanes="1" speed="{speed_mps:g}"/>'
    )
    return netconvert(folder, nodes, edges)


def light_queue(
    folder: Path,
    cars: int,
    every_s: float,
    phases: tuple[tuple[float, str], ...],
    vtype: str,
    dt_s: float,
    line_m: float = 200.0,
) -> SumoOptions:
    """``light_road`` (A ``line_m``, B 200 m, 13.9 m/s) with a static program of ``phases``
    ((duration s, state), looping) at "tl", and ``cars`` vehicles of vType "k" (its
    attributes ``vtype``) entering A at 13.9 m/s one every ``every_s``, ids c0, c1, ...
    zero-padded to one width (c00 ... c29 for 30): SUMO's options for a user-demand run."""
    net = light_road(folder, line_m, 200.0, 13.9)
    width = len(str(cars - 1))
    routes = folder / "r.rou.xml"
    routes.write_text(
        f'<routes><vType id="k" {vtype}/>\n'
        + "".join(
            f'<vehicle id="c{k:0{width}d}" type="k" depart="{every_s * k:.6g}" '
            'departSpeed="13.9"><route edges="A B"/></vehicle>\n'
            for k in range(cars)
        )
        + "</routes>\n"
    )
    light = folder / "light.add.xml"
    program = "".join(f'<phase duration="{d:g}" state="{s}"/>' for d, s in phases)
    light.write_text(
        '<additional><tlLogic id="tl" type="static" programID="p" offset="0">'
        f"{program}</tlLogic></additional>\n"
    )
    return SumoOptions(net, (light,), dt_s, 1, route_files=(routes,), user_demand=True)


def line_net(
    folder: Path, ends_m: tuple[float, ...], lanes: int, limits_mps: float | tuple[float, ...]
) -> Path:
    """A straight road of edges "A", "B", ... ending at ``ends_m`` along x (nodes n0, n1, ...),
    each with ``lanes`` lanes and its limit (one for all, or one per edge)."""
    limits = limits_mps if isinstance(limits_mps, tuple) else (limits_mps,) * len(ends_m)
    xs = (0.0, *ends_m)
    nodes = "\n".join(f'<node id="n{i}" x="{x:g}" y="0"/>' for i, x in enumerate(xs))
    edges = "\n".join(
        f'<edge id="{chr(65 + i)}" from="n{i}" to="n{i + 1}" numLanes="{lanes}" speed="{v:g}"/>'
        for i, v in enumerate(limits)
    )
    return netconvert(folder, nodes, edges)


def game_ramp_truth(folder: Path, driver_speed: str) -> tuple[SectionScenario, Any]:
    """game/ramp's main line, one run of 120 s after 300 s (the demand is past the merge's
    capacity from 300 s: a queue), half the vehicles observed, a Krauss prior with
    ``driver_speed`` (~8 s of SUMO). Returns the scenario and its loaded ground truth."""
    ramp = Path(sumo.__file__).resolve().parent / "tools" / "game" / "ramp"
    (folder / "ramp.toml").write_text(
        f"""name = "ramp"
seed = 1

[network]
kind = "sumo"
net_file = "{ramp / "ramp.net.xml"}"
route_files = ["{ramp / "ramp.rou.xml"}"]

[section]
edges = ["gneE3", "gneE7", "gneE8"]
closed = false

[instrumented]
penetration = 0.5

[simulation]
warmup_s = 300.0
duration_s = 120.0
n_runs = 1
step_length_s = 0.5

[detectors]
interval_s = 60.0
auto_spacing_m = 250.0

[policy]
prior = "krauss"
driver_speed = "{driver_speed}"
"""
    )
    sc = load_scenario(folder / "ramp.toml")
    simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(folder / "gt", sc)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def dump_toml(table: dict[str, Any]) -> str:
    """Write a scenario table (scalars, then one level of sub-tables) as TOML text."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in table.items() if not isinstance(v, dict)]
    for name, sub in table.items():
        if isinstance(sub, dict):
            lines.append(f"\n[{name}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in sub.items()]
    return "\n".join(lines) + "\n"


def scenario_table(overrides: dict[str, Any] | None = None, drop: tuple[str, ...] = ()) -> dict:
    """The paper scenario as a dict with absolute network paths, dotted ``overrides`` applied
    and dotted keys in ``drop`` removed."""
    table = tomllib.loads(PAPER_SCENARIO.read_text())
    for key in ("net_file", "routes_file"):
        table["network"][key] = str((PAPER_SCENARIO.parent / table["network"][key]).resolve())
    for dotted, value in (overrides or {}).items():
        *parents, leaf = dotted.split(".")
        node = table
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    for dotted in drop:
        *parents, leaf = dotted.split(".")
        node = table
        for p in parents:
            node = node[p]
        del node[leaf]
    return table


@pytest.fixture
def make_scenario(tmp_path: Path) -> MakeScenario:
    """Factory: ``make_scenario(overrides, name=..., drop=...)`` -> path of a scenario TOML."""

    def make(
        overrides: dict[str, Any] | None = None,
        name: str = "scenario.toml",
        drop: tuple[str, ...] = (),
    ) -> Path:
        path = tmp_path / name
        path.write_text(dump_toml(scenario_table(overrides, drop)))
        return path

    return make


def write_scenario(folder: Path, overrides: dict[str, Any] | None = None) -> Path:
    """Module-scope variant of ``make_scenario`` for fixtures that simulate once."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scenario.toml"
    path.write_text(dump_toml(scenario_table(overrides)))
    return path


# Four runs of 120 s on the paper ring: the smallest ground truth the Stage II tests train on.
SMALL_RING = {"simulation.n_runs": 4, "simulation.duration_s": 120.0}


@pytest.fixture(scope="session")
def small_ring_gt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ground truth of the paper ring with ``SMALL_RING``, simulated once. A scenario that
    differs from it only in later stages' keys (generator.*, policy.*) reads it as its own:
    the simulation depends on the seed, the fleet and simulation.* alone."""
    folder = tmp_path_factory.mktemp("small_ring")
    path = write_scenario(folder, SMALL_RING)
    assert main(["simulate", str(path), "--out", str(folder / "gt"), "--quiet"]) == 0
    return folder / "gt"


@pytest.fixture(scope="session")
def bremen() -> Section:
    """The section of SUMO's Bremen motorway example (3-4 lanes, an on-ramp merge)."""
    return read_section(
        ROOT / "sumo_nets" / "highway_bremen" / "highway.net.xml",
        ["145354574", "189597495", "E0", "191842213"],
        False,
    )


@pytest.fixture(scope="session")
def ring_two_lane_short(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth) of scenarios/ring_two_lane.toml cut to three runs (one to
    train, validate, hold out) of a 60 s warm-up and 60 s recorded (loops every 60 s): the
    fleet departs standing, over loops."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(sc, simulation=replace(sc.simulation, n_runs=3, warmup_s=60.0, duration_s=60.0))
    folder = tmp_path_factory.mktemp("r2l_short")
    simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(folder / "gt", sc)


@pytest.fixture(scope="session")
def ring_driver_follow(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground-truth folder, truth, fitted prior, its likelihood pairs, the fit's
    manifest record) of scenarios/ring_two_lane.toml cut to two runs of 40 s after a 30 s
    warm-up, with ``policy.driver_follow = "drawn"`` and 2 episodes an update: the ring of
    the driver-tau tests (tests/policy/test_driver_follow_training.py,
    tests/evaluation/test_section_driver_tau.py), simulated and fitted once."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(
        sc,
        simulation=replace(sc.simulation, n_runs=2, warmup_s=30.0, duration_s=40.0),
        policy=replace(sc.policy, driver_follow="drawn", episodes_per_update=2),
    )
    gt = simulate_section(sc, tmp_path_factory.mktemp("driver_follow") / "gt", progress=False)
    truth = load_section_truth(gt, sc)
    prior, extra, pairs = fit_residual_prior(sc, truth, truth.runs)
    return sc, Path(gt), truth, prior, pairs, extra["prior"]


def assert_one_line_error(capsys: pytest.CaptureFixture, code: int, *fragments: str) -> str:
    """The command failed as bad input (exit 2) with one ``error: ...`` line on stderr, no
    traceback, holding every one of ``fragments``; returns the line."""
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    for f in fragments:
        assert f in err, f"{f!r} not in {err!r}"
    return err


def listing(folder: Path) -> list[str]:
    """Every path below ``folder``, relative to it, sorted: what a command left there."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture(scope="module")
def keep_torch_threads() -> Iterator[None]:
    """train-generator sets torch to one thread for the whole process: restore it after the
    module (``pytestmark = pytest.mark.usefixtures("keep_torch_threads")``)."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


# ------------------------------------------------------------------ a random corridor
def corridor_table(folder: Path, net_seed: int = 3) -> dict[str, Any]:
    """A corridor drawn by netgen from ``net_seed`` into ``folder / "net"`` (open, lane counts
    change along it), as a scenario table: 30 % instrumented, 2 runs of 120 s after a 150 s
    warm-up, loops every 200 m, 30 s intervals."""
    cor = random_corridor(folder / "net", net_seed)
    return {
        "name": "corridor",
        "seed": 5,
        "network": {"kind": "sumo", "sumocfg": str(cor.sumocfg)},
        "section": {"edges": list(cor.section_edges), "closed": False},
        "instrumented": {"penetration": 0.3},
        "simulation": {"warmup_s": 150.0, "duration_s": 120.0, "n_runs": 2},
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 200.0},
    }


@pytest.fixture(scope="session")
def netgen_corridor(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """An open multi-lane corridor of 3 edges drawn by netgen (seed 4242): 3 runs of 120 s
    after a 120 s warm-up, 30 % instrumented, loops every 200 m at 30 s, a generator trained
    for 3 epochs, the lookahead observation and 8-step episodes (the section envs'):
    {"scenario", "gt", "gen"} paths (the scenario file, its ground truth, generator.pt)."""
    folder = tmp_path_factory.mktemp("netgen_corridor")
    cor = random_corridor(folder / "net", 4242, n_edges=3)
    table = {
        "name": "netgen_corridor",
        "seed": 5,
        "network": {"kind": "sumo", "sumocfg": str(cor.sumocfg)},
        "section": {"edges": list(cor.section_edges)},
        "instrumented": {"penetration": 0.3},
        "simulation": {"warmup_s": 120.0, "duration_s": 120.0, "n_runs": 3},
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 200.0},
        "generator": {"epochs": 3, "snapshot_every_s": 10.0},
        "policy": {"observation": "lookahead", "horizon": 8},
    }
    path = folder / "corridor.toml"
    path.write_text(dump_toml(table))
    gt, gen = folder / "gt", folder / "gen"
    assert main(["simulate", str(path), "--out", str(gt), "--quiet"]) == 0
    assert (
        main(["train-generator", str(path), "--data", str(gt), "--out", str(gen), "--quiet"]) == 0
    )
    return {"scenario": path, "gt": gt, "gen": gen / "generator.pt"}


# ------------------------------------------------------------------ field data (tests/fielddata)
# A small simulated ground truth on a random corridor (lane counts change along it), the
# source every field-data fixture is exported from. Here, not in a conftest of its own: two
# conftest modules shadow each other for the tests that import this one by name.
@pytest.fixture(scope="session")
def field_truth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One 120 s run (0.2 s of SUMO), 30 % instrumented, E1 loops every 200 m, 30 s intervals."""
    folder = tmp_path_factory.mktemp("field_truth")
    table = corridor_table(folder)
    table["simulation"]["n_runs"] = 1
    (folder / "corridor.toml").write_text(dump_toml(table))
    assert (
        main(["simulate", str(folder / "corridor.toml"), "--out", str(folder / "gt"), "--quiet"])
        == 0
    )
    return folder / "gt"


@pytest.fixture(scope="session")
def section(field_truth: Path) -> Section:
    return Section.read(field_truth / "section.json")


@pytest.fixture(scope="session")
def observed(field_truth: Path) -> pd.DataFrame:
    traj = pd.read_csv(field_truth / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    return traj[traj["observed"]].reset_index(drop=True)


@pytest.fixture(scope="session")
def detectors(field_truth: Path) -> pd.DataFrame:
    return pd.read_csv(field_truth / "detectors.csv", dtype={"detector_id": str})


@pytest.fixture(scope="session")
def e2_truth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ``field_truth`` corridor with the user's E2 lane-area detectors instead of loops:
    150 m from pos 50 on every lane of three edges (3, 3, 2 lanes), 30 s intervals, 120 s
    recorded. The simulate stage keeps SUMO's own E2 output and the definitions it ran under
    ``sumo/run_000`` (as the truth stage rewrites them: ``lane`` + ``length``)."""
    folder = tmp_path_factory.mktemp("e2_truth")
    cor = random_corridor(folder / "net", 3)
    defs = [
        f'    <laneAreaDetector id="e2_{e}_{k}" lane="{e}_{k}" pos="50" length="150" '
        'period="30" file="e2_user.xml"/>'
        for e, n in zip(cor.section_edges, cor.lanes_per_edge, strict=True)
        if e in ("e1", "e2", "e5")
        for k in range(n)
    ]
    (folder / "e2.add.xml").write_text("<additional>\n" + "\n".join(defs) + "\n</additional>\n")
    (folder / "corridor.toml").write_text(
        f"""name = "corridor_e2"
seed = 5

[network]
kind = "sumo"
sumocfg = {json.dumps(str(cor.sumocfg))}
additional_files = [{json.dumps(str(folder / "e2.add.xml"))}]

[section]
edges = {json.dumps(list(cor.section_edges))}
closed = false

[simulation]
warmup_s = 150.0
duration_s = 120.0
n_runs = 1

[detectors]
interval_s = 30.0
"""
    )
    out = folder / "gt"
    assert main(["simulate", str(folder / "corridor.toml"), "--out", str(out), "--quiet"]) == 0
    return out


# ------------------------------------------------------------------ the ring as a closed section
@pytest.fixture(scope="session")
def ring_loop() -> Section:
    """The paper ring's network read as a closed one-lane section (628.3 m)."""
    return read_section(NETS / "ring_r100_e4.net.xml", ["e0", "e1", "e2", "e3"], True)


@pytest.fixture(scope="session")
def ring_section_truth(tmp_path_factory: pytest.TempPathFactory) -> tuple[SectionScenario, Path]:
    """ring_paper_section's fleet on the ring, two runs of 120 s (real SUMO): one
    ground truth for every test that checks psi against the recorded passages."""
    folder = tmp_path_factory.mktemp("ring_section_truth")
    text = (ROOT / "scenarios" / "ring_paper_section.toml").read_text()
    text = text.replace("../sumo_nets/", f"{ROOT}/sumo_nets/")
    text = text.replace("duration_s = 180.0", "duration_s = 120.0").replace(
        "n_runs = 40", "n_runs = 2"
    )
    path = folder / "ring.toml"
    path.write_text(text)
    sc = load_scenario(path)
    assert (sc.simulation.duration_s, sc.simulation.n_runs) == (120.0, 2), "shipped file changed"
    simulate_section(sc, folder / "gt", progress=False)
    return sc, folder / "gt"


BREMEN_FILES = ROOT / "scenarios" / "highway_bremen_files.toml"
# Tiny Stage I and II budgets for the field-data pipeline tests (TOML, for bremen_files_with).
BREMEN_TINY = """
[generator]
epochs = 2
batch_size = 32

[policy]
updates = 1
episodes_per_update = 4
observation = "lookahead"
"""


def bremen_files_with(folder: Path, budgets: str) -> Path:
    """The shipped field-data example with absolute paths and the example's training budgets
    replaced by ``budgets`` (TOML tables placed before its ``[data]``)."""
    text = BREMEN_FILES.read_text().replace('"../sumo_nets', f'"{ROOT}/sumo_nets')
    text = re.sub(r"\n\[generator\]\nepochs = \d+\n", "\n", text)
    text = re.sub(r"\n\[policy\]\nupdates = \d+\nobservation = \"lookahead\"\n", "\n", text)
    head, data = text.split("\n[data]\n", 1)
    path = folder / "bremen_files.toml"
    path.write_text(head + budgets + "\n[data]\n" + data)
    return path


@pytest.fixture(scope="session", autouse=True)
def _one_process_pipelines() -> Iterator[None]:
    """Tests' pipelines run their stages one after the other: with their tiny budgets two
    spawned workers' start-up (importing the package) cost more than the stages gain
    (a small ring section run: 39 -> 73 s on the loaded machine). tests/pipeline/
    test_parallel.py asks for two processes explicitly. Session-scoped: a module or session
    fixture that runs a pipeline is set up before any function-scoped fixture (patched there,
    tests/pipeline/test_pipeline.py's fixture ran side by side: 64 s of CPU, not 32)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(parallel, "MAX_JOBS", 1)
        yield

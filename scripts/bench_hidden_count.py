"""Bench of the hidden-count estimate K on networks drawn from a seed: error per lane and regime.

Each network is a one-way main line of 3-5 edges (1-4 lanes each, so lane drops and gains,
250-800 m) with, by draw, an on-ramp and an off-ramp at its nodes, E1 loops placed by the
tool every 150-400 m, two car types and a truck share, and a demand that steps from one level
to another half-way through the run (free flow up to queues behind the narrowest edge or the
merge). ``simulate`` writes each ground truth (cached in ``--out``); the table is the mean
absolute error of K per lane over the snapshots of each regime (a snapshot is congested when
10% of its vehicles are at or below 5 m/s) for: ``flow_speed``, the former flow / speed
estimate; ``density``, the regime-blended density estimate alone; ``intervals``, the
stations' interval counts between stations (``truth.interval_counts``: what field data
gives; at signals the approaches by the programs, ``truth.signal_counts``); ``io_ramps_unknown``, the
passages' estimate not told where the ramps are; ``io``, the estimate ``simulate`` writes
(``k_estimate.csv``); and the mean error (bias) of ``io``. ``--ramp`` adds SUMO's
``game/ramp``, ``--signals`` its ``game/cross`` and ``game/corridor`` (queues at red
lights), ``--arterials N ...`` signalised arterials whose queues spill back from junction
to junction (``bench_arterial.py``: 1 and 2 stop 33's, other numbers drawn from that
seed), ``--examples`` the shipped section examples; ``--boundary-stations`` runs
every network with ``detectors.auto_boundary_stations`` true (else false); ``--pieces``
adds a table of each part's error in vehicles (``io_pieces``: stretches counted from the
empty start, a ramp's node, the end pieces; docs/sections.md, "Hidden count").

    .venv/bin/python scripts/bench_hidden_count.py --seed 200 --nets 8
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import sumo
import sumolib
from bench_arterial import arterial

from macromicro_sumo.cli import main as cli_main
from macromicro_sumo.data.section import at_snapshot_times
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import read_net, scenario_inputs
from macromicro_sumo.truth.hidden_count import io_pieces, k_estimates
from macromicro_sumo.truth.interval_counts import interval_record
from macromicro_sumo.truth.section_macro import detector_macro, loop_densities
from macromicro_sumo.truth.stations import PASSAGE_LAG_STEPS, StationRecord, side_junction_arcs

SLOW_MPS = 5.0  # a snapshot is congested when ...
SLOW_SHARE = 0.10  # ... this share of its vehicles is at or below SLOW_MPS
CAPACITY_VPH_LANE = 2000.0  # rough capacity of a SUMO lane [veh/h], to draw demand levels
SUMO_TOOLS = Path(sumo.__file__).resolve().parent / "tools"
SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
EXAMPLES = ("highway_bremen", "netgen_corridor", "spreewaldring")
EXAMPLE_RUNS = 2


def get_options(args: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=100, help="first network's seed")
    p.add_argument("--nets", type=int, default=8, help="networks, seeds seed .. seed + nets - 1")
    p.add_argument("--out", type=Path, default=Path("/tmp/bench_hidden_count"), help="cache")
    p.add_argument("--ramp", action="store_true", help="add SUMO's game/ramp example")
    p.add_argument(
        "--signals",
        action="store_true",
        help="add SUMO's game/cross and game/corridor (queues at fixed-time signals), 2 runs",
    )
    p.add_argument(
        "--arterials",
        type=int,
        nargs="*",
        default=[],
        help="signalised arterials (bench_arterial.py): 1 and 2 are stop 33's, any other "
        "number is drawn from it as a seed",
    )
    p.add_argument(
        "--boundary-stations",
        action="store_true",
        help="detectors.auto_boundary_stations = true (a station inside each end, either "
        "side of each ramp's node and at each signal's stop bar) on the drawn networks and "
        "the examples; else false",
    )
    p.add_argument(
        "--occupancy-loop-m",
        type=float,
        default=0.0,
        help="detectors.auto_occupancy_loop_m: dual loops, a second E1 this long (m) beside "
        "each placed point loop for its occupancy (0: point loops only; a new cache folder)",
    )
    p.add_argument(
        "--start-s",
        type=float,
        default=0.0,
        help="score each record from this time on (s): a field record starts mid-traffic, a "
        "simulation's on an empty road, which anchors the counts (signal approaches: from 240 "
        "s on, arterials 1, 2, 600-603 were 11.19 / 14.82 vehicles per lane before stop 39)",
    )
    p.add_argument(
        "--vtype-spread",
        action="store_true",
        help="arterials: each vType a seeded distribution of lengths and minGaps "
        "(truth.vtype_spread: no standing lattice; a new cache folder)",
    )
    p.add_argument(
        "--near-line",
        nargs="?",
        const=True,
        default=False,
        choices=["all", "station"],
        help="intervals: signal approaches with the near-line loops' standing queue where the "
        "free-travel bound is the largest (truth.standing; StationRecord.near_line); all: half of "
        "it on every approach (standing.NEAR_LINE_ALL_SHARE); station: on every approach, what "
        "each near-line station's loops missed of it (standing.seen_share)",
    )
    p.add_argument(
        "--pieces",
        action="store_true",
        help="also a table of each part's error (vehicles): between stations, with a ramp, "
        "the end pieces",
    )
    p.add_argument(
        "--examples",
        action="store_true",
        help=f"add the shipped section examples ({', '.join(EXAMPLES)}), {EXAMPLE_RUNS} runs each",
    )
    return p.parse_args(args)


def netconvert(folder: Path, name: str, nodes: list[str], edges: list[str]) -> Path:
    (folder / f"{name}.nod.xml").write_text("<nodes>\n" + "\n".join(nodes) + "\n</nodes>\n")
    (folder / f"{name}.edg.xml").write_text("<edges>\n" + "\n".join(edges) + "\n</edges>\n")
    net = folder / f"{name}.net.xml"
    subprocess.run(
        [
            sumolib.checkBinary("netconvert"),
            "-n", str(folder / f"{name}.nod.xml"),
            "-e", str(folder / f"{name}.edg.xml"),
            "-o", str(net),
            "--no-turnarounds", "true",
            "--no-warnings", "true",
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    return net


def build_network(folder: Path, seed: int) -> tuple[dict, str]:
    """A drawn main line with ramps and its demand; the scenario table and a description."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 6))
    lengths = rng.uniform(250.0, 800.0, n).round(1)
    lanes = rng.integers(1, 5, n)
    lanes[0] = lanes.max()  # the entry is widest: any lane drop downstream is a bottleneck
    speed = round(float(rng.uniform(22.0, 36.0)), 1)
    x = np.concatenate([[0.0], np.cumsum(lengths)])
    nodes = [f'<node id="n{i}" x="{xi:.1f}" y="0"/>' for i, xi in enumerate(x)]
    edges = [
        f'<edge id="m{i}" from="n{i}" to="n{i + 1}" numLanes="{lanes[i]}" speed="{speed}" '
        'priority="3"/>'
        for i in range(n)
    ]
    main = " ".join(f"m{i}" for i in range(n))
    routes = [f'<route id="main" edges="{main}"/>']
    flows = [("main", "main", 1.0)]
    desc = [f"lanes {'-'.join(map(str, lanes))}"]
    if n > 2 and rng.random() < 0.6:  # on-ramp at an inner node
        j = int(rng.integers(1, n - 1))
        nodes.append(f'<node id="r_in" x="{x[j] - 300:.1f}" y="-60"/>')
        edges.append(
            f'<edge id="on" from="r_in" to="n{j}" numLanes="1" speed="{min(speed, 22.0)}" '
            'priority="1"/>'
        )
        routes.append(f'<route id="onramp" edges="on {" ".join(f"m{i}" for i in range(j, n))}"/>')
        flows.append(("onramp", "onramp", float(rng.uniform(0.1, 0.3))))
        desc.append(f"on-ramp at node {j}")
    if n > 2 and rng.random() < 0.4:  # off-ramp at an inner node
        j = int(rng.integers(1, n - 1))
        nodes.append(f'<node id="r_out" x="{x[j] + 300:.1f}" y="-60"/>')
        edges.append(
            f'<edge id="off" from="n{j}" to="r_out" numLanes="1" speed="20" priority="1"/>'
        )
        routes.append(f'<route id="offramp" edges="{" ".join(f"m{i}" for i in range(j))} off"/>')
        flows.append(("offramp", "offramp", float(rng.uniform(0.05, 0.2))))
        desc.append(f"off-ramp at node {j}")
    netconvert(folder, "bench", nodes, edges)
    # Demand relative to the narrowest edge's capacity: the first half at one level, the
    # second at another (free flow up to a queue behind a lane drop or the merge).
    cap = CAPACITY_VPH_LANE * int(lanes.min())
    levels = rng.uniform(0.4, 1.4, 2).round(2)
    truck = round(float(rng.uniform(0.0, 0.2)), 2)
    half = 600
    rows = [
        "<routes>",
        '<vType id="car" length="5.0" minGap="2.5" carFollowModel="Krauss" sigma="0.5" '
        'speedDev="0.1"/>',
        '<vType id="car_idm" length="4.5" minGap="2.0" carFollowModel="IDM" accel="1.5" '
        'decel="3.0" tau="1.2" speedDev="0.1"/>',
        '<vType id="truck" length="12.0" minGap="2.5" vClass="truck" maxSpeed="25" accel="1.0" '
        'speedDev="0.05"/>',
        f'<vTypeDistribution id="mix" vTypes="car car_idm truck" '
        f'probabilities="{0.6 * (1 - truck):.3f} {0.4 * (1 - truck):.3f} {truck:.3f}"/>',
        *routes,
    ]
    for fid, route, share in flows:
        for k, (b, e) in enumerate(((0, half), (half, 3600))):
            vph = cap * levels[k] * share
            rows.append(
                f'<flow id="{fid}{k}" type="mix" route="{route}" begin="{b}" end="{e}" '
                f'vehsPerHour="{vph:.0f}" departLane="free" departSpeed="max"/>'
            )
    rows.append("</routes>")
    (folder / "bench.rou.xml").write_text("\n".join(rows) + "\n")
    desc.append(f"demand {levels[0]:.2f} -> {levels[1]:.2f} x capacity, trucks {truck:.0%}")
    table = {
        "name": f"bench_{seed}",
        "seed": seed,
        "network": {
            "kind": "sumo",
            "net_file": str(folder / "bench.net.xml"),
            "route_files": [str(folder / "bench.rou.xml")],
        },
        "section": {"edges": [f"m{i}" for i in range(n)], "closed": False},
        "instrumented": {"penetration": 0.1},
        "simulation": {"warmup_s": 200.0, "duration_s": 1000.0, "n_runs": 1},
        "detectors": {
            "interval_s": 60.0,
            "auto_spacing_m": round(float(rng.uniform(150.0, 400.0))),
            "k_window_s": 60.0,
        },
        "generator": {"snapshot_every_s": 10.0},
    }
    desc.append(f"loops every {table['detectors']['auto_spacing_m']:.0f} m")
    return table, ", ".join(desc)


def ramp_example(folder: Path) -> tuple[dict, str]:
    """SUMO's game/ramp example (a congested merge), its main line as the section."""
    game = SUMO_TOOLS / "game" / "ramp"
    table = {
        "name": "ramp",
        "seed": 1,
        "network": {
            "kind": "sumo",
            "net_file": str(game / "ramp.net.xml"),
            "route_files": [str(game / "ramp.rou.xml")],
        },
        "section": {"edges": ["gneE3", "gneE7", "gneE8"], "closed": False},
        "instrumented": {"penetration": 0.1},
        "simulation": {"warmup_s": 100.0, "duration_s": 600.0, "n_runs": 1},
        "detectors": {"interval_s": 60.0, "auto_spacing_m": 250.0, "k_window_s": 60.0},
        "generator": {"snapshot_every_s": 10.0},
    }
    return table, "SUMO game/ramp: merge, demand rising to overload"


SIGNAL_SECTIONS = {
    "cross": ("cross", ["1fi", "1si", "2o", "2fo"], "one junction, 90 s fixed-time program"),
    "corridor": (
        "corridor",
        ["gneE28", "gneE10", "gneE11", "gneE26"],
        "arterial, three fixed-time signals",
    ),
}


def signal_example(folder: Path, name: str) -> tuple[dict, str]:
    """SUMO's game/cross or game/corridor (queues at red lights), the net's own fixed-time
    programs (not the game's manual ``cross.tls.add.xml``): cross's west-east approach and
    exit, corridor's arterial; loops every 60 m, 90 s intervals (cross's cycle)."""
    sub, edges, desc = SIGNAL_SECTIONS[name]
    game = SUMO_TOOLS / "game" / sub
    table = {
        "name": name,
        "seed": 1,
        "network": {
            "kind": "sumo",
            "net_file": str(game / f"{sub}.net.xml"),
            "route_files": [str(game / f"{sub}.rou.xml")],
        },
        "section": {"edges": edges, "closed": False},
        "instrumented": {"penetration": 0.2},
        "simulation": {"warmup_s": 120.0, "duration_s": 900.0, "n_runs": 2},
        "detectors": {"interval_s": 90.0, "auto_spacing_m": 60.0, "k_window_s": 60.0},
        "generator": {"snapshot_every_s": 10.0},
    }
    return table, f"SUMO game/{sub}: {desc}"


def dump_toml(table: dict) -> str:
    lines = [f"{k} = {json.dumps(v)}" for k, v in table.items() if not isinstance(v, dict)]
    for name, sub in table.items():
        if isinstance(sub, dict):
            lines.append(f"\n[{name}]")
            lines += [f"{k} = {json.dumps(v)}" for k, v in sub.items()]
    return "\n".join(lines) + "\n"


def example_toml(name: str, boundary: bool) -> str:
    """A shipped scenario's TOML with its network paths absolute, ``EXAMPLE_RUNS`` runs and
    ``detectors.auto_boundary_stations`` = ``boundary``."""
    text = (SCENARIOS / f"{name}.toml").read_text()
    text = re.sub(r"(?m)^auto_boundary_stations = \w+\n", "", text)
    text = text.replace(
        "[detectors]\n", f"[detectors]\nauto_boundary_stations = {str(boundary).lower()}\n"
    )
    text = text.replace('"../sumo_nets/', f'"{SCENARIOS.parent / "sumo_nets"}/')
    return re.sub(r"(?m)^n_runs = \d+", f"n_runs = {EXAMPLE_RUNS}", text)


def ground_truth(folder: Path, table: dict | str) -> Path:
    """The ground truth of ``table`` (or TOML text) in ``folder/gt``, simulated once."""
    gt = folder / "gt"
    if (gt / "manifest.json").is_file():
        return gt
    toml = folder / "scenario.toml"
    toml.write_text(table if isinstance(table, str) else dump_toml(table))
    if cli_main(["simulate", str(toml), "--out", str(gt), "--quiet"]) != 0:
        raise SystemExit(f"simulate failed for {toml}")
    return gt


def read_truth(gt: Path, start_s: float) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """(trajectories, detectors, passages) of ``gt`` from ``start_s`` on: the snapshots and
    passages at or after it, the detectors' intervals that begin there or later."""
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    det = pd.read_csv(gt / "detectors.csv")
    pas = pd.read_csv(gt / "detector_passages.csv", dtype={"vehicle_id": str})
    if start_s > 0:
        traj, pas = traj[traj["time_s"] >= start_s], pas[pas["time_s"] >= start_s]
        det = det[det["begin_s"] >= start_s]
    return traj, det, pas


def errors(gt: Path, start_s: float = 0.0, near_line: bool | str = False) -> pd.DataFrame:
    """Per snapshot: regime, lanes and each estimator's K error, the record scored from
    ``start_s`` on (``read_truth``; after 0 the passages do not start from an empty road);
    ``near_line``: the interval counts' ``StationRecord.near_line``."""
    sc = json.loads((gt / "manifest.json").read_text())["scenario"]
    section = Section.read(gt / "section.json")
    traj, det, pas = read_truth(gt, start_s)
    empty = start_s <= 0
    every, window = sc["generator"]["snapshot_every_s"], sc["detectors"]["k_window_s"]
    # The smallest spacing (6.5 m) only filters macro.csv's spacing spread, not K.
    macro = detector_macro(det, pas, sc["simulation"]["warmup_s"], 6.5, section)
    dens = k_estimates(traj, macro, section, every, window)
    lag = PASSAGE_LAG_STEPS * sc["simulation"]["step_length_s"]
    unknown = k_estimates(
        traj, macro, section, every, window, StationRecord(det, pas, None, lag, from_empty=empty)
    )
    net_file = scenario_inputs(load_scenario(gt.parent / "scenario.toml")).net_file
    net = read_net(net_file)
    side = side_junction_arcs(net, section)
    record = interval_record(det, section, net, net_file, near_line)
    counts = k_estimates(traj, macro, section, every, window, record)
    hybrid = k_estimates(
        traj, macro, section, every, window, StationRecord(det, pas, side, lag, from_empty=empty)
    )
    snaps = at_snapshot_times(traj, every)
    slow = snaps.groupby(["run", "time_s"])["speed_mps"].apply(
        lambda v: (v <= SLOW_MPS).mean() >= SLOW_SHARE
    )
    keys = ["run", "time_s"]
    out = dens[[*keys, "k_true"]].copy()
    out["congested"] = slow.reindex(pd.MultiIndex.from_frame(out[keys])).to_numpy()
    out["flow_speed"] = dens["k_est_flow_speed"] - dens["k_true"]
    out["density"] = dens["k_error"]
    at = pd.MultiIndex.from_frame(out[keys])
    out["intervals"] = counts.set_index(keys)["k_error"].reindex(at).to_numpy()
    out["io_ramps_unknown"] = unknown.set_index(keys)["k_error"].reindex(at).to_numpy()
    out["io"] = hybrid.set_index(keys)["k_error"].reindex(at).to_numpy()
    out["lanes"] = float((section.n_lanes * section.lengths_m).sum() / section.lengths_m.sum())
    return out


def piece_errors(gt: Path, start_s: float = 0.0) -> pd.DataFrame:
    """Per snapshot and part of the section (``io_pieces``): its count's error (vehicles)
    and true count, from ``start_s`` on; the regime from ``errors``."""
    sc = json.loads((gt / "manifest.json").read_text())["scenario"]
    section = Section.read(gt / "section.json")
    traj, det, pas = read_truth(gt, start_s)
    if not (det["kind"] == "e1").all():
        return pd.DataFrame()
    det = det.assign(k_point_vpkm=loop_densities(det, pas))
    net_file = scenario_inputs(load_scenario(gt.parent / "scenario.toml")).net_file
    side = side_junction_arcs(read_net(net_file), section)
    snaps = at_snapshot_times(traj, sc["generator"]["snapshot_every_s"])
    rows = []
    for run, g in snaps.groupby("run"):
        times = np.sort(g["time_s"].unique())
        lag = PASSAGE_LAG_STEPS * sc["simulation"]["step_length_s"]
        record = StationRecord(det, pas, side, lag, from_empty=start_s <= 0)
        pieces, _ = io_pieces(record, section, run, times)
        by_t = g.groupby("time_s")["arc_m"]
        for name, piece in pieces.items():
            true = np.array(
                [
                    sum(((a >= lo) & (a < hi)).sum() for lo, hi in piece.arcs_m)
                    for a in (by_t.get_group(t).to_numpy() for t in times)
                ]
            )
            for t, est, tr in zip(times, piece.vehicles, true, strict=True):
                rows.append({"run": run, "time_s": t, "piece": name, "true": tr, "error": est - tr})
    return pd.DataFrame(rows)


def piece_rows(name: str, e: pd.DataFrame, p: pd.DataFrame) -> list[str]:
    """Mean absolute error, bias and mean true count (vehicles) per regime and part."""
    if p.empty:
        return []
    p = p.merge(e[["run", "time_s", "congested"]], on=["run", "time_s"])
    rows = []
    for (regime, piece), g in p.groupby(["congested", "piece"]):
        rows.append(
            f"| {name} | {'congested' if regime else 'free'} | {piece} | {len(g)} | "
            f"{g['true'].mean():.1f} | {np.abs(g['error']).mean():.2f} | "
            f"{g['error'].mean():+.2f} |"
        )
    return rows


ESTIMATORS = ("flow_speed", "density", "intervals", "io_ramps_unknown", "io")


def table_rows(name: str, desc: str, e: pd.DataFrame) -> list[str]:
    rows = []
    for regime, g in e.groupby("congested"):
        per_lane = [float(np.abs(g[c]).mean() / g["lanes"].iloc[0]) for c in ESTIMATORS]
        bias = float(g["io"].mean())
        rows.append(
            f"| {name} | {desc} | {'congested' if regime else 'free'} | {len(g)} | "
            f"{g['k_true'].mean():.0f} | "
            + " | ".join(f"{v:.2f}" for v in per_lane)
            + f" | {bias:+.1f} |"
        )
    return rows


def with_occupancy_loops(
    name: str, folder: Path, table: dict | str, desc: str, loop_m: float
) -> tuple[str, Path, dict | str, str]:
    """A bench network with ``detectors.auto_occupancy_loop_m`` = ``loop_m`` (dual loops),
    cached in its own subfolder of ``folder``."""
    folder = folder / f"occupancy_loop_{loop_m:g}m"
    folder.mkdir(exist_ok=True)
    if isinstance(table, str):
        table = table.replace("[detectors]\n", f"[detectors]\nauto_occupancy_loop_m = {loop_m}\n")
    else:
        table = {**table, "detectors": {**table["detectors"], "auto_occupancy_loop_m": loop_m}}
    return name, folder, table, f"{desc}, {loop_m:g} m occupancy loops"


def main(options: argparse.Namespace) -> bool:
    options.out.mkdir(parents=True, exist_ok=True)
    nets: list[tuple[str, Path, dict | str, str]] = []
    for seed in range(options.seed, options.seed + options.nets):
        folder = options.out / f"seed_{seed}"
        folder.mkdir(exist_ok=True)
        table, desc = build_network(folder, seed)
        table["detectors"]["auto_boundary_stations"] = options.boundary_stations
        if options.boundary_stations:
            folder = folder / "boundary_stations"
            folder.mkdir(exist_ok=True)
            desc += ", boundary stations"
        nets.append((f"seed {seed}", folder, table, desc))
    if options.ramp:
        folder = options.out / "ramp"
        if options.boundary_stations:
            folder = folder / "boundary_stations"
        folder.mkdir(parents=True, exist_ok=True)
        table, desc = ramp_example(folder)
        table["detectors"]["auto_boundary_stations"] = options.boundary_stations
        nets.append(("ramp", folder, table, desc))
    for name in SIGNAL_SECTIONS if options.signals else ():
        folder = options.out / name
        if options.boundary_stations:
            folder = folder / "boundary_stations"
        folder.mkdir(parents=True, exist_ok=True)
        table, desc = signal_example(folder, name)
        table["detectors"]["auto_boundary_stations"] = options.boundary_stations
        nets.append((name, folder, table, desc))
    for number in options.arterials:
        folder = options.out / f"arterial_{number}"
        if options.boundary_stations:
            folder = folder / "boundary_stations"
        if options.vtype_spread:
            folder = folder / "vtype_spread"
        folder.mkdir(parents=True, exist_ok=True)
        table, desc = arterial(folder, number, netconvert, options.vtype_spread)
        table["detectors"]["auto_boundary_stations"] = options.boundary_stations
        nets.append((f"arterial {number}", folder, table, desc))
    for name in EXAMPLES if options.examples else ():
        folder = options.out / name
        if options.boundary_stations:
            folder = folder / "boundary_stations"
        folder.mkdir(parents=True, exist_ok=True)
        toml = example_toml(name, options.boundary_stations)
        nets.append((name, folder, toml, f"shipped example, {EXAMPLE_RUNS} runs"))
    if options.occupancy_loop_m > 0:
        nets = [with_occupancy_loops(*net, options.occupancy_loop_m) for net in nets]
    print(
        "| network | drawn | regime | snapshots | mean K | "
        + " | ".join(ESTIMATORS)
        + " | bias (veh) |"
    )
    print("|---" * (6 + len(ESTIMATORS)) + "|")
    every = []
    for name, folder, table, desc in nets:
        e = errors(ground_truth(folder, table), options.start_s, options.near_line)
        every.append(e)
        for row in table_rows(name, desc, e):
            print(row, flush=True)
    allv = pd.concat(every, ignore_index=True)
    if options.pieces:
        print("\n| network | regime | part | snapshots | true (veh) | abs. error (veh) | bias |")
        print("|---" * 7 + "|")
        every_p = []
        for (name, folder, _, _), e in zip(nets, every, strict=True):
            p = piece_errors(folder / "gt", options.start_s).assign(net=name)
            every_p.append(p.merge(e[["run", "time_s", "congested"]], on=["run", "time_s"]))
            for row in piece_rows(name, e, p.drop(columns="net")):
                print(row, flush=True)
        allp = pd.concat(every_p, ignore_index=True)
        for (regime, piece), g in allp.groupby(["congested", "piece"]):
            print(
                f"| all | {'congested' if regime else 'free'} | {piece} | {len(g)} | "
                f"{g['true'].mean():.1f} | {np.abs(g['error']).mean():.2f} | "
                f"{g['error'].mean():+.2f} |"
            )
    for regime, g in allv.groupby("congested"):
        per_lane = [float((np.abs(g[c]) / g["lanes"]).mean()) for c in ESTIMATORS]
        print(
            f"| all | | {'congested' if regime else 'free'} | {len(g)} | "
            f"{g['k_true'].mean():.0f} | " + " | ".join(f"{v:.2f}" for v in per_lane) + " | |"
        )
    return True


if __name__ == "__main__":
    sys.exit(0 if main(get_options()) else 1)

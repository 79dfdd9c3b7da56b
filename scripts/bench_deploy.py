"""Benchmark a deployment with the policy in the loop against SUMO driving the same demand
with its own models, in the same run.

1. The Bremen example's demand (scenarios/highway_bremen.toml, one whole run: 120 s
   warm-up + 600 s): vehicle-steps/s (every vehicle in the network, every step) of
   - SUMO alone: the run's simulation steps, nothing read (SUMO's own speed);
   - the oracle deployment: the ground truth's run loop (recording trajectories) with
     SUMO driving everyone;
   - the policy deployment: the same loop, every non-instrumented vehicle on the section
     driven by the policy (``deploy.drivers.SectionSpeedDriver``: SUMO's state read once
     per step and shared with the recorder (``Simulation.vehicle_states``), SUMO's leaders
     of the driven vehicles, one batched policy call per step, the safety layer on),
   and the ratios per run (the three of a run back to back) with the load average beside
   each run: their median over ``--repeats`` runs is the figure to quote on a loaded
   machine (best of the runs too). The policy is
   ``--checkpoint`` (default runs/highway_bremen/policy/policy.pt; it must match the
   scenario's policy settings, prior included) when it exists, else an untrained residual
   on the scenario's prior (Gipps or its Krauss form) with fixed parameters near those
   fitted to Bremen (timing only: its vehicles drive as a trained policy's, so a run holds
   as many). State is read with per-vehicle getters, not subscriptions: a variable
   subscription of the same four values measured 2.4 against 1.9 us a vehicle to read on
   Bremen, and SUMO's step costs more with it.
2. The per-vehicle cost against the number of vehicles: a straight 4-lane road of 30 km
   (netconvert), N = 50 ... 2,000 vehicles placed on it at t = 0 and driven by the policy
   for ``--steps`` steps, next to SUMO driving the same N alone: microseconds per
   vehicle-step of each and of the driver's own share, and how far the curve is from flat
   (largest over smallest per-vehicle cost).
3. With ``--budget PAIRS``: PAIRS more Bremen policy runs (each beside SUMO alone), their
   thread CPU time per step split into SUMO's step, the state read, the driver's SUMO
   calls, the policy, the safety layer's safe speed, the driver's own code
   (``deploy/*.py``) and the recorder; and the ratio each run would reach with the
   driver's own code at no cost, the ceiling of any rewrite of the driver's Python and
   numpy (CPU time: the load moves it less than wall time).

    python scripts/bench_deploy.py [--repeats 5] [--steps 200] [--sizes 50 200 500 1000 2000]
        [--road-repeats 3] [--skip-bremen] [--cpu] [--budget 3]
        [--checkpoint runs/highway_bremen/policy/policy.pt] [--actor-dtype float64|float32]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import libsumo
import sumolib
import torch

from macromicro_sumo.deploy import safety
from macromicro_sumo.deploy.drivers import SectionDriver, SectionSpeedDriver
from macromicro_sumo.deploy.policy_batch import ACTOR_DTYPES, policy_batch
from macromicro_sumo.errors import UserError
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import load_section, record_run
from macromicro_sumo.truth.section_detectors import detectors_xml, place_detectors

ROOT = Path(__file__).resolve().parents[1]
LANES, ROAD_M, LIMIT_MPS = 4, 30_000.0, 30.0
# What the timings read: wall time, or with --cpu this process's CPU time (SUMO runs in it
# through libsumo), which other processes on a shared machine disturb far less.
CLOCK = [time.perf_counter]


class Counted:
    """A driver (or none) that also counts the vehicles in the network before each step."""

    def __init__(self, inner: SectionDriver | None) -> None:
        self.inner = inner
        self.vehicle_steps = 0

    def before_step(self, sim: Simulation) -> None:
        self.vehicle_steps += libsumo.vehicle.getIDCount()
        if self.inner is not None:
            self.inner.before_step(sim)


def bremen_scenario(tmp: Path):
    text = (ROOT / "scenarios" / "highway_bremen.toml").read_text()
    path = tmp / "highway.toml"
    path.write_text(text.replace('"../sumo_nets', f'"{ROOT}/sumo_nets'))
    return load_scenario(path)


def agent_for(sc, checkpoint: Path) -> tuple[Agent, str]:
    why = "none"
    if checkpoint.is_file():
        try:
            return load_policy(checkpoint, sc), str(checkpoint)
        except UserError as exc:  # trained with other settings than the scenario's
            why = str(exc)
    torch.manual_seed(0)
    if sc.policy.prior not in ("gipps", "krauss"):
        agent = Agent(64, observation=sc.policy.observation)
        return agent, f"untrained agent without a prior (timing only; checkpoint: {why})"
    # The scenario's shape: an untrained residual on Gipps' model (or its Krauss form, the
    # free term closing V - v within relax_s), with parameters near those fitted to
    # Bremen's Krauss drivers (b 4.65 m/s^2, tau 1.09 s): the vehicles drive as a trained
    # policy's do, so the run holds as many vehicles as it would.
    gipps = {
        "speed_factor": 1.0,
        "accel_mps2": 2.6,
        "decel_mps2": 4.65,
        "tau_s": 1.09,
        "min_gap_m": 2.5,
        "veh_length_m": 5.0,
        "dt_s": sc.simulation.step_length_s,
    }
    if sc.policy.prior == "krauss":
        gipps["relax_s"] = 2.0
    agent = Agent(
        64,
        observation=sc.policy.observation,
        prior=sc.policy.prior,
        prior_params=gipps,
        residual_bound_mps2=sc.policy.residual_bound_mps2,
    )
    return agent, (
        f"untrained residual on a fixed {sc.policy.prior} prior (timing only; checkpoint: {why})"
    )


def bremen_run(sc, tmp: Path, how: str, act, run: int = 0) -> tuple[float, int, dict]:
    """(wall s, vehicle-steps, counts) of one whole run of the Bremen demand."""
    inputs, section, _ = load_section(sc)
    folder = tmp / f"{how}_{run}"
    folder.mkdir()
    placed = place_detectors(sc, inputs, section)
    (folder / "det.add.xml").write_text(detectors_xml(placed, sc.detectors.interval_s))
    opts = SumoOptions(
        inputs.net_file,
        (*inputs.additional_files, folder / "det.add.xml"),
        sc.simulation.step_length_s,
        sc.seed + run,
        route_files=inputs.route_files,
        user_demand=True,
    )
    sim = Simulation(opts)
    try:
        if how == "sumo":
            n = int(round((sc.simulation.warmup_s + sc.simulation.duration_s) / sim.dt_s))
            count = Counted(None)
            t0 = CLOCK[0]()
            for _ in range(n):
                count.before_step(sim)
                sim.step()
            return CLOCK[0]() - t0, count.vehicle_steps, {}
        inner = (
            SectionSpeedDriver(sc, section, run, act, sc.deploy.safety)
            if how == "policy"
            else SectionDriver(sc, section, run)
        )
        count = Counted(inner)
        t0 = CLOCK[0]()
        _, stats = record_run(sim, sc, section, run, count)
        wall = CLOCK[0]() - t0
        return wall, count.vehicle_steps, {**inner.stats.as_dict(), **stats}
    finally:
        sim.close()


# --------------------------------------------------------------------------- budget
# The Simulation methods a speed driver calls besides the state read (libsumo behind each).
SUMO_CALLS = (
    "leaders",
    "set_speeds",
    "set_speed_mode",
    "release_speeds",
    "own_speeds",
    "left_blockers",
    "stop_lines_m",
    "lane_end_m",
    "vehicle_type",
    "vtype_shape",
    "arrived",
    "has_traffic_lights",
)


class Budget:
    """Thread CPU time [s] by part of a policy run, from timers around the parts (each
    adds ~1 us a call, so the driver's own code reads a little high): SUMO's step, the
    state read, and within the driver's ``before_step`` its SUMO calls, the policy, the
    safety layer's ``road.physics.safe_speed`` and the rest, the driver's own code."""

    def __init__(self) -> None:
        self.s: dict[str, float] = defaultdict(float)
        self.inner = 0.0  # parts timed inside the driver's before_step
        self.depth = 0  # > 0: inside the driver's before_step

    def timed(self, f, part: str, driver: bool = False):
        """``f`` timed into ``part``; a "driver: ..." part counts only inside the driver
        (the recorder asks SUMO too), ``driver``: the driver's before_step itself."""

        def g(*args, **kwargs):
            self.depth += driver
            t0 = time.thread_time()
            try:
                return f(*args, **kwargs)
            finally:
                dt = time.thread_time() - t0
                self.depth -= driver
                if driver or not part.startswith("driver") or self.depth:
                    self.s[part] += dt
                if self.depth and not driver:
                    self.inner += dt

        return g


def budget_pair(sc, tmp: Path, act) -> dict[str, float]:
    """One Bremen run 0 of SUMO alone and of the policy deployment, thread CPU time: seconds
    by part of the policy run (``Budget``), "SUMO alone" and the vehicle-steps of each."""
    CLOCK[0], clock = time.thread_time, CLOCK[0]
    b = Budget()
    patched = [(Simulation, "step", "SUMO step"), (Simulation, "vehicle_states", "state read")]
    patched += [(Simulation, n, "driver: SUMO calls") for n in SUMO_CALLS]
    patched.append((safety, "safe_speed", "driver: safe speed (road.physics)"))
    patched.append((SectionSpeedDriver, "before_step", "driver"))
    # What to put back: the owner's own attribute, or none (before_step is SectionDriver's).
    saved = [(owner, name, owner.__dict__.get(name)) for owner, name, _ in patched]
    tmp.mkdir()
    try:
        alone, vs0, _ = bremen_run(sc, tmp, "sumo", act, run=0)
        for owner, name, part in patched:
            timed = b.timed(getattr(owner, name), part, part == "driver")
            # A static method (``Simulation.vehicle_type``) stays one: a plain function set
            # on the class would be handed the instance as its first argument.
            if isinstance(owner.__dict__.get(name), staticmethod):
                timed = staticmethod(timed)
            setattr(owner, name, timed)
        timed_act = b.timed(act, "driver: policy (actor + prior)")
        timed_act.driver_speeds = getattr(act, "driver_speeds", None)
        total, vs, _ = bremen_run(sc, tmp, "policy", timed_act, run=0)
    finally:
        for owner, name, f in saved:
            if f is None:
                delattr(owner, name)
            else:
                setattr(owner, name, f)
        CLOCK[0] = clock
    own = b.s["driver"] - b.inner
    parts = {k: b.s[k] for k in ("SUMO step", "state read")}
    parts |= {k: v for k, v in b.s.items() if k.startswith("driver: ")}
    parts["driver: own code (deploy/*.py)"] = own
    parts["recorder and loop (the rest)"] = total - sum(parts.values())
    return {**parts, "SUMO alone": alone, "total": total, "vs": vs, "vs0": vs0}


def budget_run(sc, tmp: Path, act, pairs: int) -> None:
    """Print where a policy run's CPU time goes per step, beside SUMO alone: the median of
    ``pairs`` pairs of runs (``budget_pair``), and the ratio each pair would reach with the
    driver's own code at no cost."""
    got = [budget_pair(sc, tmp / f"budget_{i}", act) for i in range(pairs)]
    steps = int(
        round((sc.simulation.warmup_s + sc.simulation.duration_s) / sc.simulation.step_length_s)
    )
    print(f"\nCPU time per step of a policy run (Bremen run 0, thread CPU time, us/step, median "
          f"of {pairs} pairs of runs; load {os.getloadavg()[0]:.1f}):")  # fmt: skip
    for part in [k for k in got[0] if k not in ("total", "vs", "vs0")]:
        print(f"  {part:40s} {1e6 * statistics.median(g[part] for g in got) / steps:7.0f}")
    now = [(g["vs"] / g["total"]) / (g["vs0"] / g["SUMO alone"]) for g in got]
    free = "driver: own code (deploy/*.py)"
    ceiling = [(g["vs"] / (g["total"] - g[free])) / (g["vs0"] / g["SUMO alone"]) for g in got]
    print(
        "  policy deployment / SUMO alone per pair: "
        + ", ".join(f"{r:.3f}x" for r in now)
        + "; with the driver's own code at no cost: "
        + ", ".join(f"{r:.3f}x" for r in ceiling)
    )


def straight_road(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "n.nod.xml").write_text(
        f'<nodes>\n<node id="a" x="0" y="0"/>\n<node id="b" x="{ROAD_M:g}" y="0"/>\n</nodes>\n'
    )
    (folder / "e.edg.xml").write_text(
        f'<edges>\n<edge id="road" from="a" to="b" numLanes="{LANES}" speed="{LIMIT_MPS}"/>\n'
        "</edges>\n"
    )
    net = folder / "road.net.xml"
    subprocess.run(
        [
            sumolib.checkBinary("netconvert"),
            "--node-files",
            str(folder / "n.nod.xml"),
            "--edge-files",
            str(folder / "e.edg.xml"),
            "--output-file",
            str(net),
            "--no-warnings",
            "true",
        ],  # fmt: skip
        check=True,
        capture_output=True,
    )
    return net


def road_demand(folder: Path, n: int) -> Path:
    """n vehicles spread evenly over the lanes and the first 25 km, departing at t = 0."""
    per_lane = math.ceil(n / LANES)
    gap = 25_000.0 / per_lane
    lines = [
        "<routes>",
        '<vType id="car" length="5" minGap="2.5" accel="2.6" decel="4.5" sigma="0.5"/>',
        '<route id="r" edges="road"/>',
    ]
    for i in range(n):
        lane, k = i % LANES, i // LANES
        lines.append(
            f'<vehicle id="v{i}" type="car" route="r" depart="0" departLane="{lane}" '
            f'departPos="{25_000.0 - k * gap:.1f}" departSpeed="20"/>'
        )
    path = folder / f"road_{n}.rou.xml"
    path.write_text("\n".join([*lines, "</routes>"]) + "\n")
    return path


def road_scenario(folder: Path, net: Path, routes: Path):
    path = folder / f"{routes.stem}.toml"
    path.write_text(
        "\n".join(
            [
                'name = "straight"',
                "seed = 1",
                "[network]",
                'kind = "sumo"',
                f'net_file = "{net}"',
                f'route_files = ["{routes}"]',
                "[section]",
                'edges = ["road"]',
                "[instrumented]",
                "penetration = 0.01",
                "[simulation]",
                "step_length_s = 0.5",
                "[policy]",
                'observation = "lookahead"',
            ]
        )
        + "\n"
    )
    return load_scenario(path)


def road_run(sc, routes: Path, net: Path, act, steps: int) -> tuple[float, int, int]:
    """(wall s of ``steps`` steps, vehicle-steps, vehicles driven) after 2 settling steps;
    ``act`` None: SUMO alone."""
    _, section, _ = load_section(sc)
    sim = Simulation(SumoOptions(net, (), 0.5, 1, route_files=(routes,), user_demand=True))
    try:
        drv = SectionSpeedDriver(sc, section, 0, act, "sumo") if act is not None else None
        count = Counted(drv)
        for _ in range(2):  # every vehicle inserted and (with a policy) subscribed
            count.before_step(sim)
            sim.step()
        count.vehicle_steps = 0
        t0 = CLOCK[0]()
        for _ in range(steps):
            count.before_step(sim)
            sim.step()
        wall = CLOCK[0]() - t0
        return wall, count.vehicle_steps, len(drv.driven) if drv is not None else 0
    finally:
        sim.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--steps", type=int, default=200, help="steps per size on the straight road")
    ap.add_argument("--sizes", type=int, nargs="+", default=[50, 200, 500, 1000, 2000])
    ap.add_argument("--repeats", type=int, default=5, help="Bremen runs per method")
    ap.add_argument(
        "--road-repeats", type=int, default=3, help="straight-road runs per size (best counts)"
    )
    ap.add_argument("--skip-bremen", action="store_true", help="the straight road's curve only")
    ap.add_argument("--cpu", action="store_true", help="CPU time of this process, not wall time")
    ap.add_argument(
        "--budget",
        type=int,
        default=0,
        metavar="PAIRS",
        help="also PAIRS Bremen policy runs (each beside SUMO alone) timed by part",
    )
    ap.add_argument(
        "--checkpoint",
        type=Path,
        default=ROOT / "runs" / "highway_bremen" / "policy" / "policy.pt",
        help="the Bremen policy (policy.pt of a run of scenarios/highway_bremen.toml)",
    )
    ap.add_argument(
        "--actor-dtype",
        choices=tuple(ACTOR_DTYPES),
        help="the actor's dtype (policy_batch's actor_dtype; default: the scenario's "
        "deploy.actor_dtype, as its deployment drives)",
    )
    ap.add_argument("--actor-float32", action="store_true", help="--actor-dtype float32")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    CLOCK[0] = time.process_time if args.cpu else time.perf_counter
    clock = "CPU" if args.cpu else "wall"
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        sc = bremen_scenario(tmp)
        agent, which = agent_for(sc, args.checkpoint)
        dtype = "float32" if args.actor_float32 else args.actor_dtype or sc.deploy.actor_dtype
        act = policy_batch(agent, dtype)
        which += f" (actor in {dtype})"
        if args.skip_bremen:
            print(f"policy: {which}")
        if not args.skip_bremen:
            print(f"Bremen example's demand, one whole run ({sc.simulation.warmup_s:g} s warm-up + "
                  f"{sc.simulation.duration_s:g} s, step {sc.simulation.step_length_s} s); "
                  f"policy: {which}, safety {sc.deploy.safety}; {clock} time")  # fmt: skip
            rates: dict[str, list[float]] = {"sumo": [], "oracle": [], "policy": []}
            loads: list[float] = []
            for r in range(args.repeats):
                line = []
                for how in rates:
                    wall, vs, stats = bremen_run(sc, tmp, how, act, run=r)
                    rates[how].append(vs / wall)
                    line.append(f"{how} {vs / wall:9,.0f} veh-steps/s ({vs:,} in {wall:.2f} s)")
                    if how == "policy":
                        line.append(
                            f"driven {stats['vehicle_steps_driven']:,}, collisions "
                            f"{stats['collisions']}, teleports {stats['teleports']}"
                        )
                loads.append(os.getloadavg()[0])
                print(f"  run {r} (load {loads[-1]:.1f}): " + " | ".join(line))
            # The three of a run back to back, their ratio per run and its median over the
            # runs: on the shared 2-core machine the load moves SUMO alone by 1.6x between
            # runs, and the best-of ratio moved between 0.16x and 0.29x for the same code.
            for how in ("policy", "oracle"):
                paired = [p / s for p, s in zip(rates[how], rates["sumo"], strict=True)]
                # Three decimals: a change of 10 us a policy step moves the ratio ~0.003x.
                print(
                    f"  {how} deployment / SUMO alone per run: "
                    + ", ".join(f"{r:.3f}x" for r in paired)
                    + f"; median {statistics.median(paired):.3f}x"
                    + (" (target >= 0.3x)" if how == "policy" else "")
                )
            best = {k: max(v) for k, v in rates.items()}
            print(
                f"  best of {args.repeats}: SUMO alone {best['sumo']:,.0f}, oracle deployment "
                f"{best['oracle']:,.0f}, policy deployment {best['policy']:,.0f} veh-steps/s; "
                f"load average (1 min) {min(loads):.1f}-{max(loads):.1f}"
            )

        if args.budget:
            budget_run(sc, tmp, act, args.budget)

        print(f"\nStraight {LANES}-lane road, {ROAD_M / 1000:g} km, {args.steps} steps per size, "
              f"best of {args.road_repeats}; microseconds per vehicle-step ({clock} time):")  # fmt: skip
        net = straight_road(tmp / "road")
        print(
            f"  {'vehicles':>8} {'driven':>7} {'SUMO alone':>11} {'with policy':>12} "
            f"{'driver share':>13} {'ratio':>6} {'load':>5}"
        )
        curve: list[float] = []
        for n in args.sizes:
            routes = road_demand(tmp / "road", n)
            rsc = road_scenario(tmp / "road", net, routes)
            # Best of --road-repeats each: on a shared machine the slowest runs measure the load.
            us0 = us1 = math.inf
            for _ in range(args.road_repeats):
                w0, vs0, _ = road_run(rsc, routes, net, None, args.steps)
                w1, vs1, driven = road_run(rsc, routes, net, act, args.steps)
                us0, us1 = min(us0, 1e6 * w0 / vs0), min(us1, 1e6 * w1 / vs1)
            curve.append(us1)
            print(
                f"  {vs1 / args.steps:8.0f} {driven:7d} {us0:11.2f} {us1:12.2f} "
                f"{us1 - us0:13.2f} {us0 / us1:6.2f} {os.getloadavg()[0]:5.1f}"
            )
        # Flat: no size costs a vehicle-step much more than the cheapest (a cost growing
        # with N, a leader search along the lane, would show at the large sizes).
        print(
            f"  per-vehicle cost with the policy, largest / smallest over the sizes: "
            f"{max(curve) / min(curve):.2f}; at {args.sizes[-1]:,} / at {args.sizes[0]:,} "
            f"vehicles: {curve[-1] / curve[0]:.2f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

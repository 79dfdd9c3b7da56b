"""Benchmark: how the generator's and the env core's costs grow with the number of vehicles N.

Issue 16: "Generator and env costs grow at most linearly with the number of vehicles". On
generated rings at the paper ring's density (R = 20 N m: L / N = 125.7 m), each read as its
closed one-lane section with the paper ring's fleet and settings (``ring_paper.toml``, only
the radius and ``fleet.n_vehicles`` changed), for each N:

(a) Stage I training: seconds per epoch of Algorithm 2 (``train_section_generator``, the
    ring's K range ``generator.hidden_train`` drawn per snapshot and epoch), on the paper
    ring's 864 training and 216 validation snapshots;
(b) Stage I sampling: seconds per 1,000 completions (``complete_section``, one thread) with
    K = 4 (the same K at every N), and, for reference, K = N / 5 (a fixed share hidden: K
    placement steps over N vehicles each, so up to quadratic by construction);
(c) the env core (``SectionCore`` in real SUMO through libsumo): microseconds per env step,
    K = 4 hidden vehicles driven by random actions, the others replaying their records,
    resets every H steps included.

Costs are CPU time of this process (``time.process_time``: torch on one thread, SUMO in
the process through libsumo), which other processes on a shared machine disturb far less
than wall time (measured: at load 19 on 2 cores, wall times of one N varied 3x between
runs). The snapshots are a short SUMO ground truth of each ring (``--runs`` runs of the paper's
180 s), repeated to the counts above: an epoch's cost depends on how many snapshots it
sees, not on whether they repeat. Each cost is also divided by N relative to the smallest
N ("per vehicle": (t / N) / (t_N0 / N0)); at most linear means <= 1, and 1.25 is allowed
for timing noise on a shared machine (the old ring benchmark's bound).

    python scripts/bench_generator.py                      # N = 5 10 22 50 100
    python scripts/bench_generator.py --n 5 22 --epochs 2 --env-steps 500
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from bench_section_env import bench_core, run_core  # a sibling script: scripts/ is on the path

from macromicro_sumo.data.section import (
    SectionSnapshots,
    draw_k,
    hide_random,
    recorded_snapshots,
)
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank
from macromicro_sumo.env.section_envs import true_section_completion
from macromicro_sumo.generator.section_sampler import complete_section
from macromicro_sumo.generator.section_train import train_section_generator
from macromicro_sumo.road.ring import build_ring
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "scenarios" / "ring_paper.toml"
SPACING_M = 2 * math.pi * 100.0 / 5  # the paper ring's L / N
N_VALUES = (5, 10, 22, 50, 100)
TRAIN, VAL, COMPLETIONS = 864, 216, 1000  # the paper ring's split; completions per batch
K_FIXED = 4
TARGET_PER_VEHICLE = 1.25

DETECTORS = """<additional>
{}
</additional>
"""
DETECTOR = (
    '    <inductionLoop id="e1_e{k}" lane="e{k}_0" pos="{mid:.6f}" period="60" file="e1.out.xml"/>\n'
    '    <laneAreaDetector id="e2_e{k}" lane="e{k}_0" pos="0" endPos="{end:.6f}" period="60" '
    'file="e2.out.xml"/>'
)


def get_options(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=list(N_VALUES), help="vehicle counts N")
    ap.add_argument("--epochs", type=int, default=3, help="training epochs per N (median)")
    ap.add_argument("--runs", type=int, default=3, help="ground-truth runs per ring")
    ap.add_argument("--env-steps", type=int, default=2000, help="env steps timed per N")
    ap.add_argument("--repeats", type=int, default=3, help="timed completion batches per N")
    args = ap.parse_args(argv)
    if any(n < 5 for n in args.n) or args.epochs < 1 or args.runs < 2:
        ap.error("accepted: N >= 5 (K = 4 hidden of them), --epochs >= 1, --runs >= 2")
    return args


def ring_scenario(folder: Path, n: int, runs: int) -> Path:
    """The paper ring's file with a ring of ``n`` vehicles at its density (net, routes and
    the ring's detector file built into ``folder``)."""
    radius = n * SPACING_M / (2 * math.pi)
    name = f"ring_n{n}"
    build_ring(radius, 4, folder, name)
    edge = 2 * math.pi * radius / 4
    dets = "\n".join(DETECTOR.format(k=k, mid=edge / 2, end=edge) for k in range(4))
    (folder / f"{name}.det.add.xml").write_text(DETECTORS.format(dets))
    text = PAPER.read_text()
    for old, new in (
        ("radius_m = 100.0", f"radius_m = {radius!r}"),
        ('"../sumo_nets/ring_r100_e4.net.xml"', f'"{name}.net.xml"'),
        ('"../sumo_nets/ring_r100_e4.add.xml"', f'"{name}.add.xml"'),
        ("n_vehicles = 5 ", f"n_vehicles = {n} "),
        ("n_runs = 40", f"n_runs = {runs}"),
    ):
        assert old in text, f"{PAPER} changed: {old!r} not found"
        text = text.replace(old, new, 1)
    path = folder / f"{name}.toml"
    path.write_text(text)
    return path


def repeated(snaps: SectionSnapshots, count: int) -> SectionSnapshots:
    return snaps.take(np.arange(count) % len(snaps))


def measure(n: int, args: argparse.Namespace, work: Path) -> dict[str, float]:
    folder = work / f"n{n}"
    folder.mkdir()
    sc = load_scenario(ring_scenario(folder, n, args.runs))
    t0 = time.perf_counter()
    truth = load_section_truth(simulate_section(sc, folder / "gt", progress=False), sc)
    sim_s = time.perf_counter() - t0
    recorded = recorded_snapshots(truth, sc, truth.runs)
    rng = np.random.default_rng([sc.seed, n])
    val = repeated(recorded, VAL)
    val = hide_random(val, draw_k(val, sc.generator.hidden_train, rng), rng)
    torch.manual_seed(sc.seed)
    sc_e = dataclasses.replace(
        sc, generator=dataclasses.replace(sc.generator, min_epochs=0, patience=args.epochs + 1)
    )
    c0 = time.process_time()
    net, log = train_section_generator(
        sc_e, truth.section, repeated(recorded, TRAIN), val, progress=False, epochs=args.epochs
    )
    epoch_s = (time.process_time() - c0) / len(log)  # validation included
    torch.set_num_threads(1)
    out = {"N": n, "sim_s": sim_s, "epoch_s": epoch_s}
    for label, k in (("k4", K_FIXED), ("share", max(1, n // 5))):
        held = hide_random(repeated(recorded, COMPLETIONS), k, rng)
        ks = np.full(COMPLETIONS, k)
        brake, dt = -sc.bounds.accel_mps2[0], sc.simulation.step_length_s
        warm = complete_section(net, truth.section, held, ks, sc.generator.t_max, 0, brake, dt)
        # vehicles placed by projection (a Python fallback per failed row) after T_max trials
        out[f"projected_{label}"] = int(warm.projections.sum())
        times = []
        for seed in range(args.repeats):
            t1 = time.process_time()
            complete_section(net, truth.section, held, ks, sc.generator.t_max, seed, brake, dt)
            times.append(time.process_time() - t1)
        out[f"complete_{label}_s"] = statistics.median(times)
    episodes = hide_random(recorded, K_FIXED, rng)
    bank = build_section_bank(
        sc, truth, episodes, true_section_completion, sc.policy.horizon, sc.seed
    )
    core = SectionCore(sc, truth.section, bank, scenario_inputs(sc).net_file, seed=0)
    try:
        run_core(core, min(200, args.env_steps), rng)  # warm-up: SUMO's first loads
        out["env_us"] = 1e6 / bench_core(core, args.env_steps, rng, time.process_time)
    finally:
        core.close()
    return out


def main(args: argparse.Namespace) -> int:
    # torch imports its compiler stack on the first optimiser (seconds of CPU): not N's cost
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_generator_") as tmp:
        for n in args.n:
            rows.append(measure(n, args, Path(tmp)))
            r = rows[-1]
            print(
                f"N = {n:>4}: ground truth {r['sim_s']:.1f} s; {r['epoch_s']:.2f} s/epoch, "
                f"{r['complete_k4_s']:.3f} s / {COMPLETIONS} completions (K = 4), "
                f"{r['env_us']:.0f} us/env step; projected vehicles per 1000 completions: "
                f"{r['projected_k4']} (K = 4), {r['projected_share']} (K = {max(1, n // 5)})",
                flush=True,
            )
    n0 = rows[0]["N"]

    def per_vehicle(r: dict[str, float], key: str) -> float:
        return (r[key] / r["N"]) / (rows[0][key] / n0)

    print(
        f"\nCost against N (rings at L / N = {SPACING_M:.1f} m; per vehicle = (t / N) / "
        f"(t_{n0} / {n0}); K = 4 hidden unless said):"
    )
    print(
        f"{'N':>5} {'s/epoch':>8} {'per veh':>8} {'s/1000 compl.':>13} {'per veh':>8} "
        f"{'K=N/5: s/1000':>13} {'per veh':>8} {'us/env step':>11} {'per veh':>8}"
    )
    for r in rows:
        print(
            f"{r['N']:>5} {r['epoch_s']:>8.2f} {per_vehicle(r, 'epoch_s'):>8.2f} "
            f"{r['complete_k4_s']:>13.3f} {per_vehicle(r, 'complete_k4_s'):>8.2f} "
            f"{r['complete_share_s']:>13.3f} {per_vehicle(r, 'complete_share_s'):>8.2f} "
            f"{r['env_us']:>11.0f} {per_vehicle(r, 'env_us'):>8.2f}"
        )
    last = rows[-1]
    checks = [
        ("training epoch", per_vehicle(last, "epoch_s")),
        ("sampling, K = 4", per_vehicle(last, "complete_k4_s")),
        ("env core step", per_vehicle(last, "env_us")),
    ]
    print(f"\nAt most linear (per-vehicle ratio at N = {last['N']} <= {TARGET_PER_VEHICLE}):")
    for name, ratio in checks:
        print(f"  {name:<16} {ratio:6.2f}  {'yes' if ratio <= TARGET_PER_VEHICLE else 'NO'}")
    # Other processes on the machine slow every measure.
    print(f"load average over the last minute: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    return 0 if all(r <= TARGET_PER_VEHICLE for _, r in checks) else 1


if __name__ == "__main__":
    sys.exit(main(get_options()))

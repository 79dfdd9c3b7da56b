"""In-process A/B of a Bremen policy deployment: the same run (the Bremen example's demand,
run 0, one whole run as ``scripts/bench_deploy.py`` runs it) driven by two variants of the
deploy modules, alternated in one process (base/new, then new/base, ...), so that a change
of a few microseconds a step is seen beside the load's drift, which moves whole runs by
+-10% on a shared machine and hides it in ``bench_deploy``'s ratios.

- base: the package this interpreter imports (its checkout on PYTHONPATH);
- new: ``--modules`` of the package loaded from NEW_ROOT (another checkout or worktree of
  the repository), the rest shared with base.

Per run: thread CPU time per step of the whole loop (``truth.section.record_run``), of
SUMO's step (``Simulation.step``: what the driver's work between steps costs SUMO), of the
driver's ``before_step`` and of the action function alone; and a hash of every speed
command sent (the vehicles and the values): equal hashes, the same deployment to the bit.
Printed per pair and as medians, with the median of the per-pair differences and how many
pairs the new variant was faster in.

    PYTHONPATH=$PWD .venv/bin/python scripts/ab_deploy.py NEW_ROOT [--pairs 8]
        [--modules deploy.policy_batch deploy.drivers] [--checkpoint POLICY.pt]
        [--actor-dtype float64|float32] [--new-actor-dtype float64|float32]
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import macromicro_sumo.deploy.drivers as base_drivers
import macromicro_sumo.deploy.policy_batch as base_batch
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import load_section, record_run
from macromicro_sumo.truth.section_detectors import detectors_xml, place_detectors

HERE = Path(__file__).resolve().parent
# The driver and what its hot path is made of, each before the modules importing it (the
# merge mixin too: without it an A/B of deploy/merge_yield.py ran the base's in both arms;
# road.physics first: the driver, observation and merge mixin take count_nonzero from it,
# which a base checkout before stop 46 lacks).
MODULES = (
    "road.physics",
    "deploy.slots",
    "deploy.observe",
    "deploy.merge_yield",
    "deploy.policy_batch",
    "deploy.section_driver",
    "deploy.lane_asks",
    "deploy.driver_observe",
    "deploy.drivers",
)
# The driver's parts split from deploy/drivers.py at stop 48: a checkout before that lacks
# them, and its drivers.py imports none of them (skipped there, not an error).
SPLIT = frozenset({"deploy.section_driver", "deploy.lane_asks", "deploy.driver_observe"})
PARTS = ("total", "SUMO step", "driver", "act")


def bench_module():
    """``scripts/bench_deploy.py`` as a module (its Bremen scenario and policy loading)."""
    spec = importlib.util.spec_from_file_location("bench_deploy", HERE / "bench_deploy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def variant(
    root: Path, names: list[str], optional: frozenset[str] = frozenset()
) -> dict[str, object]:
    """``names`` (in import order) loaded from the package under ``root``, each importing
    the ones loaded before it; ``sys.modules`` left as it was (base). A name in ``optional``
    whose file ``root`` lacks is skipped (an older checkout); any other is an error."""
    full = [f"macromicro_sumo.{m}" for m in names]
    saved = {m: sys.modules.get(m) for m in full}
    got: dict[str, object] = {}
    try:
        for m in full:
            path = root / (m.replace(".", "/") + ".py")
            if not path.is_file() and m.removeprefix("macromicro_sumo.") in optional:
                continue
            if not path.is_file():
                raise SystemExit(f"{path} not found (NEW_ROOT)")
            spec = importlib.util.spec_from_file_location(m, path)
            got[m] = sys.modules[m] = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(got[m])
    finally:
        for m, module in saved.items():
            if module is None:
                sys.modules.pop(m, None)
            else:
                sys.modules[m] = module
    return got


class Timed:
    """Thread CPU time by part of the run in progress, and the speed-command hash."""

    def __init__(self) -> None:
        self.s = dict.fromkeys(PARTS, 0.0)
        self.hash = hashlib.sha256()

    def wrap(self, f, part: str):
        def g(*args, **kwargs):
            t0 = time.thread_time()
            try:
                return f(*args, **kwargs)
            finally:
                self.s[part] += time.thread_time() - t0

        return g


NOW = [Timed()]


def patch_simulation() -> None:
    """SUMO's step timed, every speed command hashed (for every run of this process)."""
    step, set_speeds = Simulation.step, Simulation.set_speeds

    def timed_step(self) -> None:
        t0 = time.thread_time()
        step(self)
        NOW[0].s["SUMO step"] += time.thread_time() - t0

    def hashed(self, vehicle_ids, speeds_mps) -> None:
        NOW[0].hash.update(np.asarray(speeds_mps, dtype=float).tobytes())
        NOW[0].hash.update("|".join(vehicle_ids).encode())
        set_speeds(self, vehicle_ids, speeds_mps)

    Simulation.step, Simulation.set_speeds = timed_step, hashed


def one_run(sc, folder: Path, driver_cls, act) -> tuple[dict[str, float], str]:
    """(seconds by part, speed-command hash) of run 0 driven by ``driver_cls`` with ``act``."""
    inputs, section, _ = load_section(sc)
    folder.mkdir()
    placed = place_detectors(sc, inputs, section)
    (folder / "det.add.xml").write_text(detectors_xml(placed, sc.detectors.interval_s))
    opts = SumoOptions(
        inputs.net_file,
        (*inputs.additional_files, folder / "det.add.xml"),
        sc.simulation.step_length_s,
        sc.seed,
        route_files=inputs.route_files,
        user_demand=True,
    )
    NOW[0] = timed = Timed()
    timed_act = timed.wrap(act, "act")
    timed_act.__dict__.update(act.__dict__)  # driver_speeds, driver_taus, stop_gap_m
    sim = Simulation(opts)
    try:
        drv = driver_cls(sc, section, 0, timed_act, sc.deploy.safety)
        drv.before_step = timed.wrap(drv.before_step, "driver")
        t0 = time.thread_time()
        record_run(sim, sc, section, 0, drv)
        timed.s["total"] = time.thread_time() - t0
    finally:
        sim.close()
    return timed.s, timed.hash.hexdigest()[:16]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("new_root", type=Path, help="the checkout whose modules are the new variant")
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--modules", nargs="+", default=list(MODULES), help="from NEW_ROOT")
    ap.add_argument(
        "--checkpoint",
        type=Path,
        default=HERE.parent / "runs" / "highway_bremen" / "policy" / "policy.pt",
        help="the Bremen policy (as bench_deploy.py's)",
    )
    ap.add_argument(
        "--actor-dtype",
        choices=tuple(base_batch.ACTOR_DTYPES),
        help="both variants' actor dtype (default: the scenario's deploy.actor_dtype)",
    )
    ap.add_argument(
        "--new-actor-dtype",
        choices=tuple(base_batch.ACTOR_DTYPES),
        help="the new variant's actor dtype alone (other commands where it differs)",
    )
    ap.add_argument("--new-actor-float32", action="store_true", help="--new-actor-dtype float32")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    bench = bench_module()
    new = variant(args.new_root.resolve(), args.modules, SPLIT)
    new_drivers = new.get("macromicro_sumo.deploy.drivers", base_drivers)
    new_batch = new.get("macromicro_sumo.deploy.policy_batch", base_batch)
    patch_simulation()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        sc = bench.bremen_scenario(tmp)
        agent, which = bench.agent_for(sc, args.checkpoint)
        dtype = args.actor_dtype or sc.deploy.actor_dtype
        new_dtype = "float32" if args.new_actor_float32 else args.new_actor_dtype or dtype
        arms = {
            "base": (base_drivers.SectionSpeedDriver, base_batch.policy_batch(agent, dtype)),
            "new": (new_drivers.SectionSpeedDriver, new_batch.policy_batch(agent, new_dtype)),
        }
        print(
            f"policy: {which}; actor {dtype} -> {new_dtype}; new: {', '.join(args.modules)} "
            f"from {args.new_root}"
        )
        steps = round(
            (sc.simulation.warmup_s + sc.simulation.duration_s) / sc.simulation.step_length_s
        )
        one_run(sc, tmp / "warm", *arms["base"])  # the first run of a process pays for loading
        got: dict[str, list[tuple[dict[str, float], str]]] = {"base": [], "new": []}
        for p in range(args.pairs):
            for arm in ("base", "new") if p % 2 == 0 else ("new", "base"):
                got[arm].append(one_run(sc, tmp / f"{arm}{p}", *arms[arm]))
            (b, hb), (n, hn) = got["base"][-1], got["new"][-1]
            print(
                f"pair {p}: "
                + " | ".join(
                    f"{part} {1e6 * b[part] / steps:7.1f} -> {1e6 * n[part] / steps:7.1f}"
                    for part in PARTS
                )
                + f" us/step; hashes {hb} {hn}",
                flush=True,
            )
        print(f"medians over {args.pairs} pairs (us/step; new - base per pair):")
        for part in PARTS:
            b = [1e6 * s[part] / steps for s, _ in got["base"]]
            n = [1e6 * s[part] / steps for s, _ in got["new"]]
            d = [y - x for x, y in zip(b, n, strict=True)]
            print(
                f"  {part:10s} base {statistics.median(b):7.1f} new {statistics.median(n):7.1f}"
                f"  diff {statistics.median(d):+6.1f}, new faster in {sum(x < 0 for x in d)}"
                f" of {len(d)}"
            )
        hashes = {h for arm in got.values() for _, h in arm}
        print(
            f"  speed commands: {'the same' if len(hashes) == 1 else 'different'} ({len(hashes)} hashes)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

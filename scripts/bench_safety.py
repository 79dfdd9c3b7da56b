"""The safety layer's own time a step at Bremen, A/B: the inputs of every call of
``BrakeHandover`` (``deploy.brake_plan``), ``leader_safe_speed`` and ``safety_cap``
(``deploy.safety``) in one Bremen policy run (``scripts/ab_deploy.py``'s run 0, the base
package driving) are recorded, then replayed through the ``deploy/brake_plan.py`` and
``deploy/safety.py`` of the base package and of NEW_ROOT (another checkout or worktree),
alternated over rounds: the median time a call of each function, and whether every output
is the same to the bit.

Why: the functions cost tens of us a step, while a whole deployment run's A/B
(``ab_deploy.py``) moves by hundreds at this machine's load; replayed alone, identical code
differs by about +-2 us a call (stop 42).

    PYTHONPATH=$PWD .venv/bin/python scripts/bench_safety.py NEW_ROOT [--rounds 5]
        [--reps 3] [--checkpoint POLICY.pt] [--duration-s S]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
FUNCTIONS = ("BrakeHandover", "leader_safe_speed", "safety_cap")
# The layer's modules in import order: safety.py may import brake_plan's names, so
# brake_plan is loaded first and stands in sys.modules while safety.py runs. A root from
# before brake_plan was split off safety.py (stop 45) has safety.py alone.
LAYER = ("deploy.brake_plan", "deploy.safety")
Call = tuple[str, tuple]


def layer_modules(root: Path) -> dict[str, ModuleType]:
    """``LAYER``'s modules loaded from the package under ``root`` (``ab_deploy.variant``:
    registered as ``macromicro_sumo.<m>`` while each loads, so a later one imports that
    root's copy of an earlier one; ``sys.modules`` left as it was), keyed by the short name;
    brake_plan.py may be missing (before stop 45)."""
    sys.path.insert(0, str(HERE))
    import ab_deploy  # noqa: PLC0415 (a script beside this one)

    safety = root / "macromicro_sumo" / "deploy" / "safety.py"
    if not safety.is_file():
        raise SystemExit(f"bench_safety.py: {safety} not found (NEW_ROOT)")
    got = ab_deploy.variant(root, list(LAYER), optional=frozenset({"deploy.brake_plan"}))
    return {m.removeprefix("macromicro_sumo."): mod for m, mod in got.items()}


def layer(modules: dict[str, ModuleType]) -> SimpleNamespace:
    """The replayed functions of one copy of the layer: ``BrakeHandover`` from brake_plan
    (from safety where the copy has no brake_plan), the others from safety."""
    safety = modules["deploy.safety"]
    plan = modules.get("deploy.brake_plan", safety)
    return SimpleNamespace(
        BrakeHandover=plan.BrakeHandover,
        leader_safe_speed=safety.leader_safe_speed,
        safety_cap=safety.safety_cap,
    )


def root_layer(root: Path) -> SimpleNamespace:
    """``layer`` of the package under ``root``."""
    return layer(layer_modules(root))


def base_layer() -> SimpleNamespace:
    """``layer`` of the package this interpreter imports."""
    import macromicro_sumo.deploy.brake_plan as plan  # noqa: PLC0415
    import macromicro_sumo.deploy.safety as safety  # noqa: PLC0415

    return layer({"deploy.brake_plan": plan, "deploy.safety": safety})


def record(checkpoint: Path, duration_s: float | None = None) -> tuple[list[Call], float]:
    """The safety-layer calls (name, copied arguments) of one Bremen run, and its step;
    ``duration_s``: the run's length after the warm-up (None: the scenario's)."""
    sys.path.insert(0, str(HERE))
    import ab_deploy  # noqa: PLC0415 (a script beside this one)

    import macromicro_sumo.deploy.brake_plan as plan  # noqa: PLC0415
    import macromicro_sumo.deploy.drivers as drivers  # noqa: PLC0415
    import macromicro_sumo.deploy.safety as safety  # noqa: PLC0415

    calls: list[Call] = []

    def copied(args: tuple) -> tuple:
        return tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args)

    # Where each is looked up when a driver runs: the class's method (drivers holds the
    # class), drivers' own name for leader_safe_speed, safety's global for safety_cap
    # (speed_commands calls it).
    handover, safe, cap = (
        plan.BrakeHandover.__call__,
        drivers.leader_safe_speed,
        safety.safety_cap,
    )

    def rec_handover(self, *args):
        calls.append(("BrakeHandover", copied(args)))
        return handover(self, *args)

    def rec_safe(*args):
        calls.append(("leader_safe_speed", copied(args)))
        return safe(*args)

    def rec_cap(*args):
        calls.append(("safety_cap", copied(args)))
        return cap(*args)

    plan.BrakeHandover.__call__, drivers.leader_safe_speed, safety.safety_cap = (
        rec_handover,
        rec_safe,
        rec_cap,
    )
    try:
        torch.set_num_threads(1)
        bench = ab_deploy.bench_module()
        with tempfile.TemporaryDirectory() as tmp_name:
            tmp = Path(tmp_name)
            sc = bench.bremen_scenario(tmp)
            if duration_s is not None:
                sim = dataclasses.replace(sc.simulation, duration_s=float(duration_s))
                sc = dataclasses.replace(sc, simulation=sim)
            agent, _ = bench.agent_for(sc, checkpoint)
            act = ab_deploy.base_batch.policy_batch(agent, sc.deploy.actor_dtype)
            ab_deploy.one_run(sc, tmp / "run", drivers.SectionSpeedDriver, act)
    finally:
        plan.BrakeHandover.__call__, drivers.leader_safe_speed, safety.safety_cap = (
            handover,
            safe,
            cap,
        )
    return calls, sc.simulation.step_length_s


def replay(funcs: SimpleNamespace, calls: list[Call], dt_s: float) -> tuple[dict[str, float], list]:
    """Seconds spent in each function over ``calls`` (one ``BrakeHandover`` for them all,
    as a run has), and every output."""
    spent = dict.fromkeys(FUNCTIONS, 0.0)
    outs = []
    run = {
        "BrakeHandover": funcs.BrakeHandover(dt_s),
        "leader_safe_speed": funcs.leader_safe_speed,
        "safety_cap": funcs.safety_cap,
    }
    for name, args in calls:
        fresh = tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args)
        f = run[name]
        t0 = time.perf_counter()
        out = f(*fresh)
        spent[name] += time.perf_counter() - t0
        outs.append(out)
    return spent, outs


def same(x, y) -> bool:
    """Equal to the bit (arrays: dtype, shape and bytes), through tuples."""
    if isinstance(x, tuple):
        return isinstance(y, tuple) and len(x) == len(y) and all(map(same, x, y))
    if isinstance(x, np.ndarray):
        return (
            isinstance(y, np.ndarray)
            and x.dtype == y.dtype
            and x.shape == y.shape
            and x.tobytes() == y.tobytes()
        )
    return type(x) is type(y) and x == y


def compare(
    base: SimpleNamespace,
    new: SimpleNamespace,
    calls: list[Call],
    dt_s: float,
    rounds: int,
    reps: int,
) -> tuple[dict[str, tuple[float, float]], bool]:
    """Per function, the median us a call of base and new over ``rounds`` alternated rounds
    of ``reps`` replays each, and whether every output of new equals base's to the bit."""
    per = {f: max(1, sum(n == f for n, _ in calls)) for f in FUNCTIONS}
    times: dict[str, dict[str, list[float]]] = {"base": {}, "new": {}}
    outs: dict[str, list] = {}
    for r in range(rounds):
        for arm in ("base", "new") if r % 2 == 0 else ("new", "base"):
            funcs = base if arm == "base" else new
            total = dict.fromkeys(FUNCTIONS, 0.0)
            for _ in range(reps):
                spent, outs[arm] = replay(funcs, calls, dt_s)
                for f in FUNCTIONS:
                    total[f] += spent[f]
            for f in FUNCTIONS:
                times[arm].setdefault(f, []).append(1e6 * total[f] / (reps * per[f]))
    medians = {
        f: (statistics.median(times["base"][f]), statistics.median(times["new"][f]))
        for f in FUNCTIONS
    }
    equal = len(outs["base"]) == len(outs["new"]) and all(map(same, outs["base"], outs["new"]))
    return medians, equal


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "new_root", type=Path, help="the checkout whose deploy/brake_plan.py and safety.py are new"
    )
    ap.add_argument("--rounds", type=int, default=5, help="alternated rounds (default 5)")
    ap.add_argument("--reps", type=int, default=3, help="replays a round (default 3)")
    ap.add_argument(
        "--checkpoint",
        type=Path,
        default=HERE.parent / "runs" / "highway_bremen" / "policy" / "policy.pt",
        help="the Bremen policy (as bench_deploy.py's)",
    )
    ap.add_argument(
        "--duration-s",
        type=float,
        default=None,
        help="the recorded run's length after the warm-up (default: the scenario's 600 s)",
    )
    args = ap.parse_args(argv)
    base = base_layer()
    new = root_layer(args.new_root.resolve())
    calls, dt = record(args.checkpoint, args.duration_s)
    medians, equal = compare(base, new, calls, dt, args.rounds, args.reps)
    counts = ", ".join(f"{f} {sum(n == f for n, _ in calls)}" for f in FUNCTIONS)
    print(
        f"{len(calls)} calls recorded (Bremen run 0: {counts}); us a call, median of {args.rounds}:"
    )
    for f, (b, n) in medians.items():
        print(f"  {f:18s} base {b:7.2f}  new {n:7.2f}  diff {n - b:+6.2f}")
    print(f"  outputs: {'the same to the bit' if equal else 'DIFFERENT'}")
    return 0 if equal else 1


if __name__ == "__main__":
    raise SystemExit(main())

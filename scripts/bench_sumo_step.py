"""Why SUMO's own step costs more in a policy deployment than with SUMO driving: the thread
CPU time of SUMO's step alone (``Simulation.step``) in variants of one Bremen run (the
example's demand, run 0, as ``scripts/bench_deploy.py`` runs it), interleaved in one
process (``--repeats`` rounds of every variant), medians per variant:

- sumo: SUMO alone, nothing read between steps;
- oracle: the ground truth's loop (``truth.section.record_run``), SUMO driving everyone;
- policy: the policy deployment (``deploy.drivers.SectionSpeedDriver``), its SUMO calls
  that change the run (speed modes, speed commands, releases) and the observations it
  acted on recorded in its first round;
- replay: the oracle's loop sending those recorded calls at the same steps, nothing else
  (the same run: its vehicle-steps and speed-command hash equal the policy's, checked):
  what SUMO's step costs under the policy's commands without the driver's work between
  steps;
- shadow: the policy's driver doing all its work each step (SUMO's leaders included) with
  nothing it sends reaching SUMO: SUMO drives everyone (the oracle's run), the driver's
  work between SUMO's steps is the policy run's;
- actor: the oracle's loop plus the policy's action function on the recorded observations
  of that step, sending nothing: the policy's numpy work alone between SUMO's steps;
- leaders: the oracle's loop plus SUMO's leader (``Simulation.leaders``) of the vehicles
  the policy would drive (non-instrumented, on the section) each step, nothing sent;
- flush: the oracle's loop plus a sum over a 32 MB array before each step (more than the
  last-level cache: SUMO's step with its caches emptied).

    PYTHONPATH=$PWD .venv/bin/python scripts/bench_sumo_step.py [--repeats 5]
        [--checkpoint POLICY.pt] [--variants sumo oracle policy replay actor leaders flush]
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import os
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from macromicro_sumo.deploy.drivers import SectionDriver, SectionSpeedDriver
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.sumo.simulation import Simulation

HERE = Path(__file__).resolve().parent
VARIANTS = ("sumo", "oracle", "policy", "replay", "shadow", "actor", "leaders", "flush")
# The Simulation methods of a speed driver that change the run (recorded, replayed).
SENT = ("set_speed_mode", "set_speeds", "release_speeds")
FLUSH = np.ones(4_000_000)  # 32 MB
HOOKED: list[SectionDriver] = [None]  # the oracle's driver of the run now


def script(name: str):
    spec = importlib.util.spec_from_file_location(name, HERE / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class Recording:
    """What one policy run sent SUMO and acted on, by step (0: before the first step)."""

    def __init__(self) -> None:
        self.on = False
        self.mute = False  # the sending methods send nothing (the "shadow" variant)
        self.step = 0  # steps made so far in the run now (every run, recording or not)
        self.sent: dict[int, list[tuple[str, tuple]]] = defaultdict(list)
        self.obs: dict[int, np.ndarray] = {}
        self.hash = hashlib.md5()

    def patch(self) -> None:
        """Simulation's sending methods recorded while ``on``, every speed command hashed,
        steps counted (on top of ``ab_deploy.patch_simulation``'s timing)."""
        for name in SENT:
            f = getattr(Simulation, name)

            def g(sim, vids, *args, _f=f, _name=name) -> None:
                vids = list(vids)
                if self.on:
                    self.sent[self.step].append((_name, (vids, *map(_copy, args))))
                if _name == "set_speeds":
                    self.hash.update(np.asarray(args[0], dtype=float).tobytes())
                    self.hash.update("|".join(vids).encode())
                if not self.mute:
                    _f(sim, vids, *args)

            setattr(Simulation, name, g)
        step = Simulation.step

        def counted(sim) -> None:
            step(sim)
            self.step += 1

        Simulation.step = counted

    def act(self, act):
        """``act`` with its observations recorded while ``on``."""

        def recorded(obs: np.ndarray) -> np.ndarray:
            if self.on:
                self.obs[self.step] = np.array(obs)
            return act(obs)

        recorded.__dict__.update(act.__dict__)  # driver_speeds, driver_taus, stop_gap_m
        return recorded


def _copy(x):
    return x if isinstance(x, (int, float)) else np.array(x)


class Hooked(SectionDriver):
    """The oracle's driver plus ``hook(sim, step)`` before each step."""

    def __init__(self, sc, section, run, hook) -> None:
        super().__init__(sc, section, run)
        self.hook = hook
        HOOKED[0] = self

    def before_step(self, sim: Simulation) -> None:
        super().before_step(sim)
        self.hook(sim, self.steps - 1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--checkpoint", type=Path, default=HERE.parent / "runs/highway_bremen/policy/policy.pt"
    )
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = run_variants(args.variants, args.repeats, args.checkpoint)
    print(f"load average (1 min) {os.getloadavg()[0]:.1f}; {args.repeats} rounds; SUMO's step, "
          "thread CPU time, us a step (median, min), vehicle-steps, us a vehicle-step:")  # fmt: skip
    for how, got in rows.items():
        steps = [g[0] for g in got]
        n, vs = 1440, got[0][1]
        print(
            f"  {how:8s} {1e6 * statistics.median(steps) / n:7.1f} {1e6 * min(steps) / n:7.1f}"
            f" {vs:>8,} {1e6 * statistics.median(steps) / vs:6.3f}  commands {got[0][2]}"
        )
    if "replay" in rows and "policy" in rows:
        same = rows["replay"][0][1:] == rows["policy"][0][1:]
        print(f"  replay = policy run (vehicle-steps, command hash): {same}")
    return 0


def run_variants(
    variants: list[str], repeats: int, checkpoint: Path
) -> dict[str, list[tuple[float, int, str]]]:
    """Per variant, (SUMO step s, vehicle-steps, command hash) of each round; Simulation's
    methods patched for the rounds, put back after."""
    saved = {n: Simulation.__dict__[n] for n in (*SENT, "step")}
    bd, ab = script("bench_deploy"), script("ab_deploy")
    bd.CLOCK[0] = time.thread_time
    ab.patch_simulation()
    rec = Recording()
    rec.patch()
    try:
        return _rounds(bd, ab, rec, variants, repeats, checkpoint)
    finally:
        for name, f in saved.items():
            setattr(Simulation, name, f)


def _rounds(bd, ab, rec: Recording, variants, repeats: int, checkpoint: Path):
    policy_first = [v for v in VARIANTS if v in variants]
    if {"replay", "actor", "leaders"} & set(policy_first) and "policy" not in policy_first:
        policy_first.insert(0, "policy")
    # the policy first: the others replay what its first round recorded
    policy_first.sort(key=lambda v: v != "policy")
    rows: dict[str, list[tuple[float, int, str]]] = defaultdict(list)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        sc = bd.bremen_scenario(tmp)
        agent, _ = bd.agent_for(sc, checkpoint)
        act = bd.policy_batch(agent, sc.deploy.actor_dtype)

        def replay(sim: Simulation, k: int) -> None:
            for name, call in rec.sent.get(k, ()):
                getattr(Simulation, name)(sim, *call)

        def actor(sim: Simulation, k: int) -> None:
            if k in rec.obs:
                act(rec.obs[k])

        def leaders(sim: Simulation, k: int) -> None:
            # the vehicles the policy would drive now in the oracle's run (its own)
            st, drv = sim.vehicle_states(), HOOKED[0]
            on, ours = drv.section.lanes.__contains__, drv.population.__contains__
            sim.leaders(
                [v for v, la in zip(st.ids, st.lanes, strict=True) if on(la) and ours(v)],
                NO_LEADER_GAP_M,
            )

        def flush(sim: Simulation, k: int) -> None:
            FLUSH.sum()

        hooks = {"oracle": lambda sim, k: None, "replay": replay, "actor": actor}
        hooks |= {"leaders": leaders, "flush": flush}
        for r in range(repeats):
            for how in policy_first:
                folder = tmp / f"{how}_{r}"
                rec.step, rec.hash = 0, hashlib.md5()
                if how == "sumo":
                    folder.mkdir()
                    s, vs, _ = bd.bremen_run(sc, folder, "sumo", act)
                    rows[how].append((s, vs, "-"))
                    continue
                rec.on = how == "policy" and r == 0
                rec.mute = how == "shadow"
                if how in ("policy", "shadow"):
                    cls = SectionSpeedDriver
                    used = rec.act(act)
                else:
                    hook = hooks[how]

                    def cls(sc, section, run, _act, _safety, _hook=hook):
                        return Hooked(sc, section, run, _hook)

                    used = act
                count = bd.Counted(None)
                orig = Simulation.step

                def counting(sim, _orig=orig, _count=count) -> None:
                    _count.vehicle_steps += len(sim.vehicle_states().ids)
                    _orig(sim)

                Simulation.step = counting
                try:
                    parts, _ = ab.one_run(sc, folder, cls, used)
                finally:
                    Simulation.step = orig
                rec.on = rec.mute = False
                rows[how].append(
                    (parts["SUMO step"], count.vehicle_steps, rec.hash.hexdigest()[:12])
                )
    return dict(rows)


if __name__ == "__main__":
    raise SystemExit(main())

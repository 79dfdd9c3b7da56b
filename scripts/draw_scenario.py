"""Write a scenario on a network drawn from a seed, to try the tool where nobody tuned it.

``--kind motorway`` draws ``bench_hidden_count.build_network``'s main line (3-5 edges of
1-4 lanes, an on-ramp and/or off-ramp, demand stepping at t = 600 s, a Krauss car / IDM car /
truck mix); ``--kind arterial`` draws ``bench_arterial.draw_arterial``'s signalised arterial.
The scenario file sets the keys README's "Your own network" names and a budget that ends in
~10 min on 2 cores; ``--variant k`` adds the settings the examples use (Krauss-form prior,
``lookahead_gap``, ``driver_speed = "memory"``), ``--variant d`` keeps every default.

    python scripts/draw_scenario.py --seed 501 --out drawn/501
    macromicro run drawn/501/k501.toml --out runs/k501

Motorway seeds give the networks docs/deploy.md measures as "drawn NNN" (501: lanes
4-2-1-1-4; 549: 3-3-2-3 with both ramps). Arterial seeds draw ``bench_arterial``'s nets, with
netconvert's 90 s programs: not the "arterial 521 / 528" of stops 38-41, whose scratch
script also redrew the signal programs and demand (hS, stop 42: 120 / 114 observed drivers
on the train + val runs here against 261 / 224 there).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_arterial import arterial  # noqa: E402
from bench_hidden_count import build_network, netconvert  # noqa: E402

DEPLOY_METHODS = ["policy", "idm_calibrated", "sumo_default", "oracle", "oracle_population"]


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return repr(v)


def to_toml(table: dict) -> str:
    top = [f"{k} = {toml_value(v)}" for k, v in table.items() if not isinstance(v, dict)]
    parts = ["\n".join(top)]
    for name, sub in table.items():
        if isinstance(sub, dict):
            rows = "\n".join(f"{k} = {toml_value(v)}" for k, v in sub.items())
            parts.append(f"[{name}]\n{rows}")
    return "\n\n".join(parts) + "\n"


def scenario(table: dict, kind: str, variant: str) -> dict:
    """The drawn table with the budget and, for ``k``, the examples' settings."""
    t = {k: (dict(v) if isinstance(v, dict) else v) for k, v in table.items()}
    t["name"] = f"{variant}{t['seed']}"
    t["instrumented"] = {"penetration": 0.1}
    if kind == "motorway":
        t["simulation"] = {"warmup_s": 150.0, "duration_s": 600.0}
        t["detectors"] = {"interval_s": 60.0, "auto_spacing_m": 250.0}
    # arterials keep their own: 120 s + 900 s, loops every 100 m, 90 s intervals (a cycle)
    t["simulation"].update(step_length_s=0.5, n_runs=4)
    t["bounds"] = {"accel_mps2": [-4.5, 2.6]}
    t["generator"] = {**t.get("generator", {}), "epochs": 20}
    t["policy"] = {"updates": 10, "episodes_per_update": 16}
    if variant == "k":
        t["policy"].update(prior="krauss", observation="lookahead_gap", driver_speed="memory")
    t["evaluation"] = {"lf_trials": 2, "fcd_episodes": 0}
    t["deploy"] = {"methods": DEPLOY_METHODS}
    return t


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, required=True, help="the network's seed")
    p.add_argument("--kind", choices=["motorway", "arterial"], default="motorway")
    p.add_argument("--variant", choices=["k", "d"], default="k", help="see the module doc")
    p.add_argument("--out", type=Path, required=True, help="a new or empty folder")
    a = p.parse_args(argv)
    if not 0 <= a.seed < 2**32:
        print(f"draw_scenario: --seed {a.seed}: give an integer in [0, 2**32)", file=sys.stderr)
        return 2
    if a.out.exists() and any(a.out.iterdir()):
        print(f"draw_scenario: {a.out} is not empty; give a new folder", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    folder = a.out.resolve()
    if a.kind == "motorway":
        table, desc = build_network(folder, a.seed)
    else:
        table, desc = arterial(folder, a.seed, netconvert)
    scen = scenario(table, a.kind, a.variant)
    path = folder / f"{scen['name']}.toml"
    head = f"# scripts/draw_scenario.py --seed {a.seed} --kind {a.kind}: {desc}\n"
    path.write_text(head + to_toml(scen))
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

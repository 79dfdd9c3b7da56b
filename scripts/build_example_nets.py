"""Copy example networks from SUMO's own distribution into sumo_nets/ (and build one corridor).

Why copies: a scenario must not depend on where the eclipse-sumo wheel is installed, nor
change silently when a newer wheel edits its examples. Each folder gets a README naming the
origin (wheel version, path, licence) and every change made here, and a .sumocfg.

Run: .venv/bin/python scripts/build_example_nets.py [--out sumo_nets]
"""

from __future__ import annotations

import argparse
import importlib.metadata
import shutil
import sys
from pathlib import Path

import sumo

from macromicro_sumo.sumo.netgen import random_corridor

GAME = Path(sumo.SUMO_HOME) / "tools" / "game"
SUMO_VERSION = importlib.metadata.version("eclipse-sumo")
CORRIDOR_SEED = 7
LICENCE = (
    "Eclipse Public License 2.0 (EPL-2.0), like the rest of SUMO "
    "(https://www.eclipse.org/legal/epl-2.0/); SPDX: EPL-2.0 OR GPL-2.0-or-later."
)


def _sumocfg(net: str, routes: list[str], adds: list[str]) -> str:
    """A minimal .sumocfg: inputs only, so the tool chooses step, seed and outputs."""
    lines = ["<sumoConfiguration>", "    <input>", f'        <net-file value="{net}"/>']
    lines.append(f'        <route-files value="{",".join(routes)}"/>')
    if adds:
        lines.append(f'        <additional-files value="{",".join(adds)}"/>')
    return "\n".join([*lines, "    </input>", "</sumoConfiguration>", ""])


def _edit(text: str, old: str, new: str, what: str) -> str:
    """Replace ``old`` exactly once: a changed upstream file must fail here, not drift."""
    if text.count(old) != 1:
        raise SystemExit(f"{what}: expected '{old}' once, found {text.count(old)} times")
    return text.replace(old, new)


def _origin(folder: str) -> str:
    return (
        f"Copied from the eclipse-sumo {SUMO_VERSION} wheel (PyPI), "
        f"`sumo/tools/game/{folder}/`, by `scripts/build_example_nets.py`.\n\n"
        f"Licence: {LICENCE}\n"
    )


def highway_bremen(out: Path) -> None:
    """The Bremen motorway of SUMO's 'highway' game: 3-lane motorway with an on-ramp."""
    src = GAME / "highway"
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "highway.net.xml", out / "highway.net.xml")
    routes = (src / "highway.rou.xml").read_text()
    routes = _edit(routes, 'vehsPerHour="7500"', 'vehsPerHour="3600"', "highway.rou.xml")
    (out / "highway.rou.xml").write_text(routes)
    (out / "ramp_green.add.xml").write_text(
        "<additional>\n"
        "    <!-- Added by scripts/build_example_nets.py: the game's ramp light J2 is red for\n"
        "         10000 s (the player switches it); this program keeps it green. -->\n"
        '    <tlLogic id="J2" type="static" programID="always_green" offset="0">\n'
        '        <phase duration="10000" state="GG"/>\n'
        "    </tlLogic>\n"
        "</additional>\n"
    )
    (out / "highway.sumocfg").write_text(
        _sumocfg("highway.net.xml", ["highway.rou.xml"], ["ramp_green.add.xml"])
    )
    (out / "README.md").write_text(
        "# highway_bremen\n\n"
        "A motorway in Bremen imported from OpenStreetMap (SUMO's 'highway' game): 3-lane\n"
        "carriageway with an on-ramp merging on edge `E0` (4 lanes), speed limit 44.44 m/s.\n\n"
        + _origin("highway")
        + "\nFiles:\n\n"
        "- `highway.net.xml`: unchanged.\n"
        "- `highway.rou.xml`: the main flow `highway` is cut from 7500 to 3600 veh/h. At 7500\n"
        "  veh/h the three lanes cannot take the flow (insertions back up: 46 vehicles waiting\n"
        "  after 900 s) and ~100 vehicles sit on the 1.9 km section; 3600 veh/h gives 42-64.\n"
        "  The ramp flow (probability 0.167 per s, ~600 veh/h) and both vTypes are unchanged;\n"
        "  the vTypes have explicit lengths (5.0 m) and SUMO's default Krauss model.\n"
        "- `ramp_green.add.xml` (new): the ramp's traffic light `J2` is red for 10000 s in the\n"
        "  game, where the player opens it; without this program the ramp only fills up\n"
        "  (108 vehicles standing after 900 s) and nothing merges.\n"
        "- `highway.sumocfg` (new): inputs only (the game has a GUI settings file instead).\n"
    )


def spreewaldring(out: Path) -> None:
    """The Spreewaldring race circuit of SUMO's 'racing' game: a closed loop."""
    src = GAME / "racing"
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "spreewaldring.net.xml", out / "spreewaldring.net.xml")
    shutil.copyfile(src / "rerouter.add.xml", out / "rerouter.add.xml")
    routes = (src / "racing.rou.xml").read_text()
    routes = _edit(routes, '<vType id="racecar"', '<vType id="racecar" length="5"', "racing")
    routes = _edit(routes, 'end="1.2" period="0.1"', 'end="3.0" period="0.1"', "racing")
    (out / "racing.rou.xml").write_text(routes)
    (out / "spreewaldring.sumocfg").write_text(
        _sumocfg("spreewaldring.net.xml", ["racing.rou.xml"], ["rerouter.add.xml"])
    )
    (out / "README.md").write_text(
        "# spreewaldring\n\n"
        "The Spreewaldring race circuit imported from OpenStreetMap (SUMO's 'racing' game):\n"
        "single-lane track, speed limit 27.78 m/s everywhere. Two rerouters keep the cars\n"
        "lapping: on `172927073#0` they get destination `172927073#5`, on `172927073#5` they\n"
        "get `172927073#0`, so they circle `172927073#0..#5, 172927499#0, 172927499#1`\n"
        "(2478 m; the loop via `172927073#6`/`#7` and the short links 243040316/243040319\n"
        "are not used). Measured: all cars stay on the circuit for 1200 s; each reroute\n"
        "appends a lap to the vehicle's route. The 2-lane `165986*` edges (pit lane) are not\n"
        "connected to the circuit.\n\n" + _origin("racing") + "\nFiles:\n\n"
        "- `spreewaldring.net.xml`, `rerouter.add.xml`: unchanged.\n"
        "- `racing.rou.xml`: the vType `racecar` had no length (SUMO would take 5 m from its\n"
        '  vClass `vip`); `length="5"` is now explicit. The flow `cars` ends at 3.0 s instead\n'
        "  of 1.2 s: 30 cars + `ego` = 31 vehicles instead of 13 (5 per km is too sparse for\n"
        '  spacing statistics). `minGap="0"`, `speedDev="0.3"` and `emergencyDecel="9"`\n'
        "  are the game's and are kept.\n"
        "- `spreewaldring.sumocfg` (new): inputs only (the game's also sets GUI and outputs).\n"
    )


def netgen_corridor(out: Path) -> None:
    """A random one-way corridor from ``macromicro_sumo.sumo.netgen`` with a fixed seed."""
    c = random_corridor(out, seed=CORRIDOR_SEED, name="corridor")
    rows = "\n".join(
        f"| `{e}` | {k} | {length:.1f} | {v:.2f} |"
        for e, k, length, v in zip(
            c.section_edges, c.lanes_per_edge, c.lengths_m, c.speeds_mps, strict=True
        )
    )
    (out / "README.md").write_text(
        "# netgen_corridor\n\n"
        f"Built by `macromicro_sumo.sumo.netgen.random_corridor(seed={CORRIDOR_SEED})` with the\n"
        f"netconvert of eclipse-sumo {SUMO_VERSION} (`scripts/build_example_nets.py`): a\n"
        "one-way corridor nobody designed, with lane counts and speed limits that change\n"
        f"between edges. Demand: {c.vehs_per_hour:g} veh/h in two flows, vType `car_idm`\n"
        "(IDM, 4.5 m) and `car_krauss` (Krauss, 5.0 m).\n\n"
        "| edge | lanes | length [m] | limit [m/s] |\n|---|---|---|---|\n" + rows + "\n"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parents[1] / "sumo_nets")
    args = parser.parse_args(argv)
    highway_bremen(args.out / "highway_bremen")
    spreewaldring(args.out / "spreewaldring")
    netgen_corridor(args.out / "netgen_corridor")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A copy of a section scenario whose demand's vTypes are seeded distributions of lengths and
minGaps (``truth.vtype_spread``): its standing queues do not sit on SUMO's 7.5 m lattice.

The route files are written spread into ``--out`` (seed: the scenario's, or ``--seed``), the
scenario TOML beside them with every network path absolute and the route files replaced;
then ``macromicro simulate OUT/NAME.toml --out GT`` (or ``run``) as for the original.

    .venv/bin/python scripts/spread_scenario.py /work/scratch/hF46/drawn/a1161/k1161.toml \
        --out /tmp/s1161
"""

from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

from macromicro_sumo.truth.vtype_spread import SPREAD_MEMBERS, spread_routes


def get_options(args: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", type=Path, help="a section scenario TOML with route_files")
    p.add_argument("--out", type=Path, required=True, help="folder of the copy")
    p.add_argument("--seed", type=int, default=None, help="the draws' seed (default: scenario's)")
    p.add_argument("--members", type=int, default=SPREAD_MEMBERS, help="members per vType")
    return p.parse_args(args)


def spread_scenario(toml: Path, out: Path, seed: int | None, members: int) -> Path:
    """Write the spread copy of ``toml`` into ``out``; returns the copy's TOML."""
    text = toml.read_text()
    table = tomllib.loads(text)
    net = table.get("network", {})
    if "sumocfg" in net or not net.get("route_files"):
        raise SystemExit(
            f"{toml}: network.route_files is needed (the demand's files to spread); "
            "accepted: net_file + route_files, no sumocfg"
        )
    seed = int(table.get("seed", 0)) if seed is None else seed
    out.mkdir(parents=True, exist_ok=True)
    here = toml.resolve().parent
    routes = []
    for i, name in enumerate(net["route_files"]):
        src = (here / name).resolve()
        routes.append(str(spread_routes(src, out / f"spread_{i}_{src.name}", seed + i, members)))
    lines = []
    section = ""
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("["):
            section = stripped
        key = stripped.split("=", 1)[0].strip()
        if section == "[network]" and key == "route_files":
            line = f"route_files = {json.dumps(routes)}"
        elif section == "[network]" and key in ("net_file", "additional_files"):
            value = net[key]
            absolute = (
                str((here / value).resolve())
                if isinstance(value, str)
                else [str((here / v).resolve()) for v in value]
            )
            line = f"{key} = {json.dumps(absolute)}"
        lines.append(line)
    dst = out / toml.name
    dst.write_text(
        f"# {toml} with its vTypes spread (scripts/spread_scenario.py, seed {seed}, "
        f"{members} members)\n" + "\n".join(lines) + "\n"
    )
    return dst


def main(options: argparse.Namespace) -> bool:
    print(spread_scenario(options.scenario, options.out, options.seed, options.members))
    return True


if __name__ == "__main__":
    sys.exit(0 if main(get_options()) else 1)

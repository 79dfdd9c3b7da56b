"""Loading a scenario file of any kind: TOML -> the ring or the section dataclasses."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path
from typing import Any

from macromicro_sumo.errors import UserError
from macromicro_sumo.files import refuse_comma
from macromicro_sumo.scenario.data import build_data
from macromicro_sumo.scenario.fields import build_table
from macromicro_sumo.scenario.ring import Scenario, check_consistency
from macromicro_sumo.scenario.ring_as_section import ring_to_section
from macromicro_sumo.scenario.section import SectionScenario, build_section_scenario

# Which wing reads a ring file (top-level ``road``): its own ring modules (the default), or
# the section wing, the file mapped by ``scenario.ring_as_section``. A section file is a
# section either way.
ROADS = ("ring", "section")


def read_scenario_toml(path: str | Path) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The raw tables of a scenario file: (scenario table, its ``[sweep]`` table or None)."""
    path = Path(path)
    file = str(path)
    if not path.is_file():
        raise UserError(f"{file}: scenario file not found")
    try:
        table = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{file}: malformed TOML ({exc})") from None
    except UnicodeDecodeError:
        raise UserError(f"{file}: not a text file (malformed TOML)") from None
    return table, table.pop("sweep", None)


def load_scenario(
    path: str | Path, overrides: dict[str, Any] | None = None, *, allow_sweep: bool = False
) -> Any:
    """Load and validate a scenario TOML; ``overrides`` maps dotted keys to values (sweeps).

    A ring file with ``road = "section"`` (or that override) loads as the section scenario
    it maps to (``scenario.ring_as_section.ring_to_section``).

    A ``[sweep]`` table is for ``macromicro batch``, which passes ``allow_sweep=True`` and
    one variant's values as ``overrides``; elsewhere it is an error.
    """
    path = Path(path)
    file = str(path)
    table, sweep = read_scenario_toml(path)
    if sweep is not None and not allow_sweep:
        raise UserError(
            f"{file}: has a [sweep] table; run its variants with `macromicro batch {file}`"
        )
    for dotted, value in (overrides or {}).items():
        node = table
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    road = table.pop("road", None)
    if road not in (None, *ROADS):
        raise UserError(
            f"{file}: road = {road!r} is not accepted; accepted: one of 'ring', 'section'"
        )
    network = table.get("network")
    kind = network.get("kind", "ring") if isinstance(network, dict) else "ring"
    if kind == "sumo":
        if road == "ring":
            raise UserError(
                f"{file}: road = 'ring' is for ring files; [network] kind = 'sumo' is a section: "
                "accepted 'section' or remove the key"
            )
        return build_section_scenario(table, file, str(path.resolve()))
    if road == "section" and kind == "ring":
        # Issue 16: the ring file read as the closed one-lane section of its net (opt-in
        # until the ring wing goes; the ring wing stays the default).
        section = ring_to_section(table, path.resolve().parent, file)
        return build_section_scenario(section, file, str(path.resolve()))
    if kind != "ring":
        raise UserError(
            f"{file}: network.kind = {kind!r} is not accepted; accepted: one of 'ring', 'sumo'"
        )
    network.pop("kind", None)
    sc = build_table(Scenario, table, "", file)
    sc = dataclasses.replace(sc, source=str(path.resolve()))
    check_consistency(sc, file)
    for key in ("net_file", "routes_file"):
        p = sc.resolve(getattr(sc.network, key))
        if not p.is_file():
            raise UserError(f"{file}: network.{key} = {p} does not exist")
        refuse_comma(p, f"{file}: network.{key}")
    return sc


def scenario_from_dict(d: dict[str, Any], source: str) -> Any:
    """Rebuild a scenario stored in a checkpoint or manifest (already validated once).

    Also takes ``to_dict()`` straight from memory: its tuples become the lists a file holds,
    so the builders see the same shapes either way.
    """
    d = json.loads(json.dumps(d))
    if d.get("network", {}).get("kind") == "sumo":
        d = dict(d)
        data = build_data(d.pop("data", None) or {}, source)  # nested tables: its own builder
        sc = build_table(SectionScenario, d, "", source)
        return dataclasses.replace(sc, source=source, data=data)
    return dataclasses.replace(build_table(Scenario, d, "", source), source=source)

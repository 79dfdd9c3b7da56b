"""Loading a scenario file: TOML -> the section dataclasses (a ring file is read as the closed
one-lane section of its generated ring network, ``scenario.ring_as_section``)."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.ring_as_section import ring_to_section
from macromicro_sumo.scenario.section import build_section_scenario

# The top-level ``road`` key chose the wing that read a ring file until stop 25; there is one
# road model now, so only "section" (what every file is) is accepted, for files that say it.
ROADS = ("section",)


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

    A ring file (``[network]`` without ``kind = "sumo"``) loads as the section scenario it
    maps to (``scenario.ring_as_section.ring_to_section``).

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
    if road == "ring":
        raise UserError(
            f"{file}: road = 'ring' was removed (stop 25): a ring file runs as the closed "
            "one-lane section of its net; accepted 'section' or remove the key"
        )
    if road not in (None, *ROADS):
        raise UserError(f"{file}: road = {road!r} is not accepted; accepted: 'section'")
    network = table.get("network")
    kind = network.get("kind", "ring") if isinstance(network, dict) else "ring"
    if kind == "ring":
        # Issue 16: the paper's ring is the closed one-lane section of its generated net.
        table = ring_to_section(table, path.resolve().parent, file)
    elif kind != "sumo":
        raise UserError(
            f"{file}: network.kind = {kind!r} is not accepted; accepted: one of 'ring', 'sumo'"
        )
    return build_section_scenario(table, file, str(path.resolve()))

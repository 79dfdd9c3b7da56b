"""Shared fixtures: small copies of the paper's ring scenario, written into tmp folders."""

from __future__ import annotations

import json
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAPER_SCENARIO = ROOT / "scenarios" / "ring_paper.toml"
NETS = ROOT / "sumo_nets"

# Small enough that a whole simulate stage takes a fraction of a second.
SMALL = {"simulation.n_runs": 2, "simulation.duration_s": 120.0}

MakeScenario = Callable[..., Path]


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def dump_toml(table: dict[str, Any]) -> str:
    """Write a scenario table (scalars, then one level of sub-tables) as TOML text."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in table.items() if not isinstance(v, dict)]
    for name, sub in table.items():
        if isinstance(sub, dict):
            lines.append(f"\n[{name}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in sub.items()]
    return "\n".join(lines) + "\n"


def scenario_table(overrides: dict[str, Any] | None = None, drop: tuple[str, ...] = ()) -> dict:
    """The paper scenario as a dict with absolute network paths, dotted ``overrides`` applied
    and dotted keys in ``drop`` removed."""
    table = tomllib.loads(PAPER_SCENARIO.read_text())
    for key in ("net_file", "routes_file"):
        table["network"][key] = str((PAPER_SCENARIO.parent / table["network"][key]).resolve())
    for dotted, value in (overrides or {}).items():
        *parents, leaf = dotted.split(".")
        node = table
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    for dotted in drop:
        *parents, leaf = dotted.split(".")
        node = table
        for p in parents:
            node = node[p]
        del node[leaf]
    return table


@pytest.fixture
def make_scenario(tmp_path: Path) -> MakeScenario:
    """Factory: ``make_scenario(overrides, name=..., drop=...)`` -> path of a scenario TOML."""

    def make(
        overrides: dict[str, Any] | None = None,
        name: str = "scenario.toml",
        drop: tuple[str, ...] = (),
    ) -> Path:
        path = tmp_path / name
        path.write_text(dump_toml(scenario_table(overrides, drop)))
        return path

    return make


def write_scenario(folder: Path, overrides: dict[str, Any] | None = None) -> Path:
    """Module-scope variant of ``make_scenario`` for fixtures that simulate once."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scenario.toml"
    path.write_text(dump_toml(scenario_table(overrides)))
    return path


@pytest.fixture(scope="session")
def scenario_writer() -> Callable[[Path, dict[str, Any] | None], Path]:
    return write_scenario

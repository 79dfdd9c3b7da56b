"""The files of a small section scenario that a test writes for itself: its route file and
its scenario TOML, one way for every test (each names only what its case is about)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from conftest import dump_toml


def vtype(type_id: str, **attrs: float | str) -> str:
    """A ``<vType>`` element of id ``type_id`` with SUMO's attributes ``attrs`` (numbers as
    ``%g``)."""
    text = " ".join(
        f'{k}="{v:g}"' if isinstance(v, float | int) else f'{k}="{v}"' for k, v in attrs.items()
    )
    return f'<vType id="{type_id}" {text}/>'


def routes_file(
    path: Path, vtypes: Sequence[str] = (), flows: Sequence[str] = (), routes: Sequence[str] = ()
) -> Path:
    """``path``, a SUMO route file of the given XML elements, one a line in this order:
    ``vtypes`` (vType, vTypeDistribution), ``routes`` (route) and ``flows`` (flow, vehicle)."""
    lines = "".join(f"    {e}\n" for e in (*vtypes, *routes, *flows))
    path.write_text(f"<routes>\n{lines}</routes>\n")
    return path


def section_scenario(
    path: Path,
    net: Path,
    routes: Path,
    edges: Sequence[str],
    *,
    seed: int,
    penetration: float,
    simulation: dict[str, Any],
    detectors: dict[str, Any],
    name: str | None = None,
    **tables: dict[str, Any],
) -> Path:
    """``path``, a scenario TOML (named ``name``, else after its stem): the section
    ``edges`` (open) of ``net`` with the demand ``routes``, ``penetration`` of the vehicles
    instrumented, the given ``[simulation]`` and ``[detectors]`` and further tables
    (``policy``, ``bounds``, ``deploy``, ...)."""
    table = {
        "name": name or path.stem,
        "seed": seed,
        "network": {"kind": "sumo", "net_file": str(net), "route_files": [str(routes)]},
        "section": {"edges": list(edges)},
        "instrumented": {"penetration": penetration},
        "simulation": simulation,
        "detectors": detectors,
        **tables,
    }
    path.write_text(dump_toml(table))
    return path

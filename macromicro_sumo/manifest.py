"""Provenance for every output folder: versions, the scenario as loaded, seed, command."""

from __future__ import annotations

import platform
import sys
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from macromicro_sumo.scenario.section import SectionScenario


def package_versions() -> dict[str, str]:
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in (
        "macromicro-sumo",
        "eclipse-sumo",
        "libsumo",
        "sumolib",
        "torch",
        "numpy",
        "pandas",
        "gymnasium",
    ):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


def build_manifest(sc: SectionScenario, command: str, stage: str) -> dict[str, Any]:
    return {
        "stage": stage,
        "scenario_name": sc.name,
        "scenario_file": sc.source,
        "scenario_sha256": sc.digest(),
        "scenario": sc.to_dict(),
        "seed": sc.seed,
        "command": command,
        "versions": package_versions(),
    }

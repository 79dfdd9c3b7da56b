"""The versions of SUMO and libsumo in use (``macromicro doctor``)."""

from __future__ import annotations

import subprocess
from importlib.metadata import PackageNotFoundError, version

import sumolib

from macromicro_sumo.sumo.simulation import api_version


def versions() -> dict[str, str]:
    """Versions of the SUMO binary and of libsumo in use."""
    sumo_bin = sumolib.checkBinary("sumo")
    first = subprocess.run([sumo_bin, "--version"], capture_output=True, text=True).stdout
    first = first.splitlines()
    return {
        "sumo_binary": sumo_bin,
        "sumo": first[0].strip() if first else "unknown",
        "libsumo": _dist_version("libsumo"),
        "libsumo_api": api_version(),
    }


def _dist_version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return "unknown"

"""A step's per-vehicle libsumo calls on libsumo's C++ functions themselves
(``sumo/libsumo_cxx.cpp``, built by setup.py where a C++ compiler is found), else through
their SWIG wrappers by
``sumo.reads``' loops: the same functions with the same arguments in the same order, so the
same values. Why: the wrapper's argument parsing and heap copy of the ID cost about as much
as many a getter itself (~450,000 calls on Bremen's policy run, ~5% of its instructions;
``scripts/bench_instructions.py``, stop 49). Where the compiled module is not built, found no
libsumo function, or answers that it cannot (an ID or output not of its form, an exception
in SUMO such as an unknown vehicle's), the wrappers are asked, and raise as before.

``MACROMICRO_SUMO_DIRECT=0`` in the environment at import switches it off (A/B runs, tests
of the wrappers' path). No libsumo here: the callers in ``sumo.simulation`` hand the
wrappers in."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence

import numpy as np

from macromicro_sumo.sumo import reads

try:  # sumo/libsumo_cxx.cpp, where setup.py built it
    from macromicro_sumo.sumo import libsumo_cxx as lib
except ImportError:  # not built: the wrappers answer
    lib = None
if lib is not None and (not lib.available() or os.environ.get("MACROMICRO_SUMO_DIRECT") == "0"):
    lib = None


def floats(
    codes: str, getters: tuple[Callable[[str], float], ...], ids: Sequence[str]
) -> np.ndarray:
    """``reads.floats(getters, ids)``: (k, n) float64, ``codes`` naming the k getters
    ("p" getLanePosition, "s" getSpeed, "a" getAcceleration, "o" getSpeedWithoutTraCI)."""
    if lib is not None:
        out = np.empty((len(codes), len(ids)))
        if lib.floats(codes, ids, out):
            return out
    return reads.floats(getters, ids)


def vehicle_ids(getter: Callable[[], tuple[str, ...]]) -> tuple[str, ...]:
    """``getter()`` of the compiled getIDList: the vehicles on the road, SUMO's order."""
    got = None if lib is None else lib.ids()
    return getter() if got is None else got


def lanes(getter: Callable[[str], str], ids: Sequence[str]) -> list[str]:
    """``reads.each(getter, ids)`` of getLaneID."""
    got = None if lib is None else lib.lanes(ids)
    return reads.each(getter, ids) if got is None else got


def leaders(getter: Callable, ids: Sequence[str], dist_m: float) -> list[tuple[str, float]]:
    """``reads.each(getter, ids, dist_m)`` of the compiled getLeader: (leader ID, gap),
    ("", -1.0) where none."""
    got = None if lib is None else lib.leaders(ids, dist_m)
    return reads.each(getter, ids, dist_m) if got is None else got


def send(setter: Callable[[str, float], object], ids: Sequence[str], values: np.ndarray) -> None:
    """``reads.send(setter, ids, values)`` of setSpeed (``values`` float64 as long)."""
    if lib is None or not lib.send(ids, values):
        reads.send(setter, ids, values)

"""A step's per-vehicle calls into libsumo (its compiled getters, setSpeed) in one C loop
each (``sumo/calls.c``, built by setup.py where a C compiler is found), else by ``map``
and ``np.fromiter``: the same calls with the same arguments in the same order, so the same
values. Why: per vehicle, map's step, a fresh argument tuple and numpy's conversion of
each answer cost more than many a getter itself; on Bremen's policy run ~1,000 items a
step (``scripts/bench_instructions.py``, stop 48). No libsumo here: the callers in
``sumo.simulation`` hand the functions in."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from itertools import repeat

import numpy as np

try:  # sumo/calls.c, where setup.py built it
    from macromicro_sumo.sumo import calls
except ImportError:  # not built: map and np.fromiter answer
    calls = None


def floats(getters: tuple[Callable[[str], float], ...], ids: Sequence[str]) -> np.ndarray:
    """(k, n): each of the k ``getters`` of each vehicle (float64), as k times
    ``np.fromiter(map(getter, ids), float, n)``; in C item by item (a vehicle's k values,
    then the next vehicle's) where built and ``ids`` is a list or tuple."""
    n = len(ids)
    if calls is not None:
        out = np.empty((len(getters), n))
        if calls.floats(getters, ids, out):
            return out
    return np.array([np.fromiter(map(g, ids), float, n) for g in getters]).reshape(len(getters), n)


def each(f: Callable, ids: Sequence[str], *arg: float) -> list:
    """``list(map(f, ids))``, or with one more argument ``list(map(f, ids, repeat(arg)))``."""
    got = None if calls is None else calls.objects(f, ids, *arg)
    if got is None:  # not built, or not a list or tuple of IDs
        got = list(map(f, ids, *(repeat(a) for a in arg)))
    return got


def send(f: Callable[[str, float], object], ids: Sequence[str], values: np.ndarray) -> None:
    """``f(id, value)`` for each vehicle, ``values`` a float64 vector as long (Python
    floats passed, not numpy scalars)."""
    if calls is None or not calls.send(f, ids, values):
        list(map(f, ids, values.tolist()))


def codes(mapping: dict, keys: Sequence[str], default: int | None = None) -> np.ndarray:
    """int64 of ``mapping.get(key, default)`` for each key (default None:
    ``mapping[key]``, KeyError where missing), as ``np.fromiter(map(...), np.int64, n)``:
    a step's vehicle -> row or code look-ups."""
    n = len(keys)
    if calls is not None:
        out = np.empty(n, np.int64)
        if calls.lookup(mapping, keys, default, out):
            return out
    if default is None:
        return np.fromiter(map(mapping.__getitem__, keys), np.int64, n)
    return np.fromiter(map(mapping.get, keys, repeat(default)), np.int64, n)


def leader_codes(
    leaders: list[tuple[str, float]], index: dict, code: dict, vids: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of the driven vehicles ``vids`` and their ``leaders`` (``Simulation.leaders``):
    SUMO's gaps, each leader's ``index`` (its row; -1 off the road) and the own and
    leaders' ``code`` (0: missing), (2n,) own first: ``deploy.observe.observe_rows``'
    look-ups, each in one C loop where built."""
    n = len(vids)
    if calls is not None:
        gap, row, shape = np.empty(n), np.empty(n, np.int64), np.empty(2 * n, np.int64)
        if calls.lookup(code, vids, 0, shape[:n]) and calls.pairs(
            leaders, index, code, gap, row, shape[n:]
        ):
            return gap, row, shape
    lead_ids, gaps = zip(*leaders, strict=False)  # pairs by construction: no check (1 us)
    gap = np.fromiter(gaps, float, n)
    return gap, codes(index, lead_ids, -1), codes(code, [*vids, *lead_ids], 0)

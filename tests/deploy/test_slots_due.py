"""``LaneCache.due`` through road/kernels.c's ``lane_due``: numpy's indices exactly, for
any cache state; a slot outside the cache and a step that is not an int go to numpy's
form (which raises or wraps as before)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from macromicro_sumo.deploy import slots as slots_module
from macromicro_sumo.deploy.slots import NOT_ASKED, LaneCache

kernels = pytest.importorskip(
    "macromicro_sumo.road.kernels", reason="road/kernels.c not built (no C compiler)"
)


def numpy_due(cache: LaneCache, slots: np.ndarray, lanes: np.ndarray, step) -> np.ndarray:
    return ((cache.lane[slots] != lanes) | (cache.again[slots] <= step)).nonzero()[0]


def test_the_same_indices_as_numpy() -> None:
    assert slots_module._lane_due is kernels.lane_due  # the slots module uses it
    rng = np.random.default_rng(48)
    for cap in (1, 4, 64, 256):
        cache = LaneCache(cap, math.nan)
        for _ in range(60):
            n = int(rng.integers(0, 2 * cap + 1))
            slots = rng.integers(0, cap, n)
            lanes = rng.integers(-1, 5, n)
            cache.lane[:] = rng.integers(-1, 5, cap)
            cache.again[:] = rng.choice([-math.inf, math.inf, math.nan, 3.0, 7.5, 10.0], cap)
            cache.lane[rng.random(cap) < 0.1] = NOT_ASKED
            step = int(rng.integers(0, 12))
            got = cache.due(slots, lanes, step)
            want = numpy_due(cache, slots, lanes, step)
            assert got.dtype == want.dtype and got.tolist() == want.tolist()
    # 2**53 + 1 is no float64: compared as numpy rounds it.
    cache = LaneCache(2, math.nan)
    cache.lane[:] = 1
    cache.again[:] = [2.0**53, 2.0**53 + 2]
    big = 2**53 + 1
    assert (
        cache.due(np.array([0, 1]), np.array([1, 1]), big).tolist()
        == numpy_due(cache, np.array([0, 1]), np.array([1, 1]), big).tolist()
    )


def test_forms_the_kernel_does_not_take_go_to_numpy() -> None:
    cache = LaneCache(4, math.nan)
    cache.lane[:] = [0, 1, 2, 3]
    cache.again[:] = [1.0, 5.0, 9.0, math.inf]
    lanes = np.array([0, 1, 0])
    out = np.empty(3, np.int64)
    assert kernels.lane_due(cache.lane, cache.again, np.array([0, 1, 9]), lanes, 4, out) == -1
    assert kernels.lane_due(cache.lane, cache.again, np.array([0, 1, -1]), lanes, 4, out) == -1
    assert kernels.lane_due(cache.lane, cache.again, np.array([0, 1, 2]), lanes, 4.0, out) == -1
    assert kernels.lane_due(cache.lane, cache.again, np.array([0, 1, 2]), lanes, 4, out) == 2
    assert out[:2].tolist() == [0, 2]
    # numpy's form answers them: a negative slot wraps, one past the end raises.
    assert cache.due(np.array([0, 1, -1]), lanes, 4).tolist() == [0, 2]
    with pytest.raises(IndexError):
        cache.due(np.array([0, 1, 9]), lanes, 4)
    assert cache.due(np.array([0, 1, 2]), lanes, 5.0).tolist() == [0, 1, 2]

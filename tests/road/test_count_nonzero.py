"""``road.physics.count_nonzero``: np.count_nonzero's count of an array (no axis), the
compiled function without the wrapper's dispatch where numpy has it."""

from __future__ import annotations

import numpy as np

from macromicro_sumo.road.physics import count_nonzero


def test_it_counts_as_np_count_nonzero() -> None:
    rng = np.random.default_rng(0)
    for a in (
        rng.random(42) < 0.3,  # a step's masks
        np.zeros(0, dtype=bool),
        rng.normal(size=17) * (rng.random(17) < 0.5),  # floats (offsets, lane ends)
        np.array([np.nan, 0.0, -0.0, np.inf]),
        np.array(True),
    ):
        got = count_nonzero(a)
        assert got == np.count_nonzero(a) and isinstance(got, (int, np.integer))
    assert count_nonzero(np.array([np.nan, 0.0, -0.0, np.inf])) == 2


def test_numpy_2_gives_the_compiled_function() -> None:
    if int(np.__version__.split(".")[0]) >= 2:
        assert type(count_nonzero).__name__ == "builtin_function_or_method"
    else:
        assert count_nonzero is np.count_nonzero

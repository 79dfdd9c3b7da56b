"""road/kernels.c's ``own_columns`` (``deploy.observe.observe_rows``' speed, delta v and
look-ahead distance columns): numpy's values to the bit, and False with nothing written
for any operand it does not take (tests/deploy/test_observe_kernel.py holds the whole
observation equal with and without the kernels)."""

from __future__ import annotations

import numpy as np
import pytest

kernels = pytest.importorskip(
    "macromicro_sumo.road.kernels", reason="road/kernels.c not built (no C compiler)"
)


def numpy_columns(obs, rows, codes, speeds, pos, lead_v, arc_per_m, arc0, ahead) -> np.ndarray:
    obs = obs.copy()
    speed = speeds[rows]
    obs[:, 0] = speed
    obs[:, 3] = speed - lead_v
    if ahead:
        arc = arc_per_m[codes]
        arc *= pos[rows]
        arc += arc0[codes]
        obs[:, 5] -= arc
    return obs


def test_the_same_values_to_the_bit() -> None:
    rng = np.random.default_rng(3)
    for n, big, lanes in ((1, 1, 2), (42, 60, 9), (300, 400, 30)):
        for ahead in (True, False):
            obs = rng.uniform(-50, 3000, (n, 6))
            rows = rng.permutation(big)[:n]
            codes = rng.integers(0, lanes, n)
            speeds, pos = rng.uniform(0, 40, big), rng.uniform(0, 500, big)
            lead_v = rng.uniform(0, 40, n)
            arc_per_m = rng.choice([1.0, 0.9987, 1.0043, np.nan], lanes)
            arc0 = rng.uniform(0, 2000, lanes)
            args = (rows, codes, speeds, pos, lead_v, arc_per_m, arc0, ahead)
            want = numpy_columns(obs, *args)
            assert kernels.own_columns(obs, *args) is True
            assert obs.tobytes() == want.tobytes()


def test_other_forms_left_to_numpy() -> None:
    obs = np.full((3, 6), 7.0)
    rows, codes, speeds = np.array([0, 2, 1]), np.array([1, 0, 1]), np.array([1.0, 2.0, 3.0])
    col = np.array([0.5, 1.0])
    good = [obs, rows, codes, speeds, speeds, speeds, col, col, True]
    for i, bad in (
        (0, np.full((3, 5), 7.0)),  # no room for the look-ahead's distance
        (0, np.full((3, 6), 7.0, np.float32)),
        (0, np.full((6, 6), 7.0)[::2]),
        (1, np.array([0, 3, 1])),  # a row past the speeds
        (2, np.array([1, 0, 2])),  # a lane code past the table
        (5, np.ones(4)),  # the leaders' speeds not one per vehicle
    ):
        args = list(good)
        args[i] = bad
        assert kernels.own_columns(*args) is False
        assert (obs == 7.0).all()
    good[0] = np.full((3, 4), 7.0)  # no look-ahead: four columns do
    good[-1] = False
    assert kernels.own_columns(*good) is True
    assert good[0][:, 0].tolist() == [1.0, 3.0, 2.0]
